"""`robtraj poses`: per-frame tool poses of a recording."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .._errors import UserError
from . import _output


def register(sub) -> argparse.ArgumentParser:
    from ..estimate import weighting_schemes

    p = sub.add_parser(
        "poses",
        help="per-frame 6-DOF tool poses from the LED measurements",
        description=(
            "Register the LED constellation from the recording's static segments, weight "
            "each LED per frame and fit the tool pose (camera frame) in every frame."
        ),
    )
    p.add_argument("recording", metavar="REC.h5")
    p.add_argument("-o", "--out", required=True, metavar="POSES.h5")
    p.add_argument(
        "--weighting",
        default="led_noise",
        choices=weighting_schemes(),
        help="LED weighting scheme (default: led_noise, see docs)",
    )
    p.add_argument(
        "--window",
        type=int,
        default=None,
        metavar="N",
        help="LED-variance window [frames] (default: about 0.1 s)",
    )
    p.add_argument(
        "--nominal",
        action="store_true",
        help="use the nominal /tool constellation instead of registering it",
    )
    p.add_argument("--json", metavar="PATH", help="write a machine-readable summary")
    p.add_argument("--force", action="store_true", help="overwrite POSES.h5")
    p.set_defaults(func=run)
    return p


def summarise(est, rec) -> dict:
    from ..estimate import errors_against

    v = est.valid
    out = {
        "frames": int(v.size),
        "valid_frames": int(v.sum()),
        "median_rms_um": float(np.nanmedian(est.rms[v]) * 1e6) if v.any() else None,
        "median_leds_used": float(np.median(est.n_used)),
        "weighting": est.weighting,
        "window_frames": est.window,
        "constellation_source": est.constellation_source,
        "notes": list(est.notes),
    }
    if est.registration is not None:
        out["registration_uncertainty_um"] = {
            str(int(i)): round(float(u) * 1e6, 3)
            for i, u in zip(est.led_ids, est.registration.uncertainty)
            if np.isfinite(u)
        }
        out["unreferenced_leds"] = {str(k): v for k, v in est.registration.reasons.items()}
    if rec.truth is not None and v.any():
        pe, ae = errors_against(
            est, rec.truth.tool_pose.position, rec.truth.tool_pose.quaternion_wxyz
        )
        out["truth_position_rms_um"] = float(np.sqrt(np.nanmean(pe**2)) * 1e6)
        out["truth_orientation_rms_mdeg"] = float(np.degrees(np.sqrt(np.nanmean(ae**2))) * 1e3)
    return out


def run(args: argparse.Namespace) -> int:
    from .._recording_reader import open_recording
    from ..estimate import estimate_poses, write_poses

    out = Path(args.out)
    # the LED positions stay in the file, read chunk by chunk by every pass over them
    with open_recording(args.recording) as rec:
        _output.check([out, args.json], force=args.force)
        if args.window is not None and args.window < 2:
            raise UserError(f"--window must be at least 2 frames, got {args.window}")
        est = estimate_poses(
            rec, weighting=args.weighting, window=args.window, register=not args.nominal
        )
    with _output.new_file(out) as tmp:
        write_poses(est, tmp, recording=args.recording)
    s = summarise(est, rec)
    line = (
        f"wrote {out}: {s['valid_frames']}/{s['frames']} frames with a pose, median residual "
        f"{s['median_rms_um']:.1f} µm, {s['median_leds_used']:.0f} LEDs per frame, "
        f"constellation {s['constellation_source']}, weighting {s['weighting']}"
    )
    if "truth_position_rms_um" in s:
        line += (
            f"; against truth: {s['truth_position_rms_um']:.1f} µm RMS, "
            f"{s['truth_orientation_rms_mdeg']:.2f} mdeg RMS"
        )
    print(line)
    for note in est.notes:
        print(f"note: {note}")
    _output.write_json(args.json, s)
    return 0
