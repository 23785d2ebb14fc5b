"""Full pose pipeline on a 10-minute, 1 kHz, 18-LED recording (issue 3).

The recording is a simulated 60 s `paper` run tiled ten times along time (the pipeline
sees 600 000 frames with the same statistics). Reports the wall time of
`estimate_poses` (variance, registration, weighting, Procrustes; JIT compile measured
separately by a first call on a short slice), frames/s against real time, and peak RSS.

    python benchmarks/bench_poses.py [--minutes 10] [--weighting led_noise]
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np

import robtraj  # noqa: F401  (x64)
from robtraj.estimate import estimate_poses
from robtraj.sim import simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--weighting", default="led_noise")
    ap.add_argument("--json", metavar="PATH")
    a = ap.parse_args()
    base = simulate("paper", seed=0, duration=60.0, rate=1000.0)
    reps = max(1, int(round(a.minutes)))
    n0 = base.n_frames
    rec = base.replace(
        time=np.concatenate([base.time + 60.0 * k for k in range(reps)]),
        frame_index=np.arange(n0 * reps, dtype=np.uint64),
        positions=np.concatenate([base.positions] * reps),
        status=np.concatenate([base.status] * reps),
        temperature=np.concatenate([base.temperature] * reps),
        program=None,
        truth=None,
        robot=None,
    )
    short = rec.replace(
        time=rec.time[:5000],
        frame_index=rec.frame_index[:5000],
        positions=rec.positions[:5000],
        status=rec.status[:5000],
        temperature=rec.temperature[:5000],
    )
    t0 = time.perf_counter()
    estimate_poses(short, weighting=a.weighting)
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    est = estimate_poses(rec, weighting=a.weighting)
    wall = time.perf_counter() - t0
    duration = rec.time[-1] - rec.time[0]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res = {
        "frames": rec.n_frames,
        "recording_s": round(float(duration), 1),
        "wall_s": round(wall, 2),
        "frames_per_s": round(rec.n_frames / wall),
        "real_time_factor": round(duration / wall, 2),
        "first_call_on_5000_frames_s": round(warm, 2),
        "peak_rss_mib": round(peak),
        "valid_fraction": float(est.valid.mean()),
        "weighting": a.weighting,
    }
    print(
        f"robtraj poses ({a.weighting}) on {rec.n_frames} frames ({duration / 60:.1f} min at 1 kHz): "
        f"{wall:.1f} s = {rec.n_frames / wall:,.0f} frames/s, {duration / wall:.1f}× faster than real "
        f"time; JIT compile + first call on 5000 frames {warm:.1f} s; peak RSS {peak:.0f} MiB"
    )
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
