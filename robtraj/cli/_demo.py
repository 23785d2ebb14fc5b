"""`robtraj demo`: the whole pipeline on a simulated recording."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="simulate a recording and run the whole pipeline on it",
        description=(
            "Simulate an LED-tool recording of the paper's trajectory (linear segment, "
            "reorientation in place, perpendicular segment), estimate per-frame poses with "
            "uniform and LED-variance weighting, and write figures to DIR."
        ),
    )
    p.add_argument("--out", default="robtraj-demo", metavar="DIR", help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..estimate import errors_against, estimate_poses, write_poses
    from ..recording import write_recording
    from ..report._demo_figures import pose_comparison_figure, visibility_figure
    from ..sim import simulate

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rec = simulate("paper", seed=args.seed)
    rec_path = out / "paper.h5"
    write_recording(rec, rec_path, overwrite=True)
    vis = rec.visible
    print(
        f"simulated {rec_path}: {rec.n_frames} frames at 1000 Hz, {rec.n_leds} LEDs, "
        f"{vis.sum(1).min()}–{vis.sum(1).max()} seen per frame"
    )
    results = {}
    for scheme in ["uniform", "inverse_variance", "led_noise"]:
        est = estimate_poses(rec, weighting=scheme)
        write_poses(est, out / f"poses_{scheme}.h5", recording=str(rec_path), overwrite=True)
        pe, ae = errors_against(
            est, rec.truth.tool_pose.position, rec.truth.tool_pose.quaternion_wxyz
        )
        results[scheme] = (est, pe, ae)
        print(
            f"poses ({scheme:>16}): {est.valid.mean() * 100:.1f} % of frames, error against "
            f"truth {np.sqrt(np.nanmean(pe**2)) * 1e6:.1f} µm RMS, "
            f"{np.degrees(np.sqrt(np.nanmean(ae**2))) * 1e3:.1f} mdeg RMS"
        )
    fig1 = visibility_figure(rec, results["led_noise"][0], out / "led_visibility.png")
    fig2 = pose_comparison_figure(rec, results, out / "weighting_comparison.png")
    print(f"figures: {fig1}, {fig2}")
    print(f"demo finished in {time.perf_counter() - t0:.0f} s; results in {out}/")
    return 0
