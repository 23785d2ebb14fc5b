"""`robtraj deviation`: path deviation of the measured TCP from the commanded path."""

from __future__ import annotations

import argparse

import numpy as np

from . import _analysis_inputs, _output


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "deviation",
        help="path deviation and orientation error against the program",
        description=(
            "Measured TCP poses (base frame, through CALIB.json) against the commanded path "
            "(linear moves, orientation by slerp): point-to-segment distance on a k-d-tree "
            "match constrained to be monotone in path progress, and the single-angle "
            "orientation error."
        ),
    )
    _analysis_inputs.add_arguments(p)
    p.add_argument("--tum", metavar="DIR", help="also export measured and commanded TUM files")
    p.set_defaults(func=run)
    return p


def deviation_of(rec, bf):
    """DeviationResult of base-frame poses `bf` against the program of `rec`."""
    from ..analysis import commanded_path, path_deviation

    step = np.nanmedian(np.linalg.norm(np.diff(bf.position, axis=0), axis=1))
    spacing = float(np.clip(step / 2 if np.isfinite(step) and step > 0 else 1e-4, 1e-5, 1e-3))
    ref = commanded_path(rec.program, spacing)
    return ref, path_deviation(ref, bf.position, bf.quaternion_wxyz)


def run(args: argparse.Namespace) -> int:
    _output.check([args.json], [args.tum], force=args.force)
    rec, calib, bf = _analysis_inputs.load(args)
    ref, dev = deviation_of(rec, bf)
    s = dev.summary()
    doc = {
        "summary": s.to_json(),
        "frames_jumped_unconstrained": int(np.sum(dev.jumped)),
        "frames_held": int(np.sum(dev.held)),
        "calibration_undetermined": _analysis_inputs.undetermined_rigid(calib),
        "calibration_weak": _analysis_inputs.weak_rigid(calib),
    }
    print(
        f"path deviation over {s.n} frames on linear moves: max {s.distance_max * 1e3:.3f} mm, "
        f"RMS {s.distance_rms * 1e3:.3f} mm; orientation error max "
        f"{np.degrees(s.orientation_max):.4f}°, RMS {np.degrees(s.orientation_rms):.4f}°"
    )
    if doc["frames_jumped_unconstrained"]:
        print(
            f"note: in {doc['frames_jumped_unconstrained']} frames the unconstrained nearest "
            "neighbour lies on another pass of the path; the monotone match was used"
        )
    if args.tum:
        from pathlib import Path

        from ..analysis import write_tum

        out = Path(args.tum)
        v = bf.valid
        with _output.new_folder(out) as tmp:
            write_tum(tmp / "measured.tum", bf.time, bf.position, bf.quaternion_wxyz, v)
            write_tum(tmp / "commanded.tum", bf.time, dev.foot, dev.foot_quaternion_wxyz, v)
        print(f"TUM trajectories in {out}/ (measured.tum, commanded.tum)")
    _analysis_inputs.write_json(args.json, doc, args.warnings)
    return 0
