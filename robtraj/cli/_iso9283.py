"""`robtraj iso9283`: the ISO 9283 performance characteristics."""

from __future__ import annotations

import argparse

import numpy as np

from . import _analysis_inputs, _output


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "iso9283",
        help="ISO 9283 pose, distance, path, corner and velocity characteristics",
        description=(
            "Detect the test poses and cycles from the program, then compute AP/RP (position "
            "and orientation, ISO components a, b, c and the single angle), vAP, AD/RD, "
            "stabilisation time and overshoot, drift, AT/RT, CR/CO and AV/RV/FV."
        ),
    )
    _analysis_inputs.add_arguments(p)
    p.set_defaults(func=run)
    return p


def iso_of(rec, bf):
    from ..analysis.iso9283 import iso9283

    return iso9283(
        rec.program, bf.time, bf.position, bf.quaternion_wxyz, segment=rec.program.segment
    )


def print_table(res) -> None:
    print(f"{'pose':>5} {'cycles':>6} {'AP [mm]':>9} {'RP [mm]':>9} {'AP∠ [°]':>9} {'RP∠ [°]':>9}")
    for p in res.poses:
        print(
            f"{p.name:>5} {p.n_cycles:>6} {p.AP * 1e3:9.4f} {p.RP * 1e3:9.4f} "
            f"{np.degrees(p.AP_angle):9.5f} {np.degrees(p.RP_angle):9.5f}"
        )
    for path in res.paths:
        d = path.to_json()
        keys = [k for k in ("AT_mm", "RT_mm", "AV_percent", "RV_percent", "FV_mm_per_s") if k in d]
        print(
            f"path {path.name}: " + ", ".join(f"{k} {d[k]:.4g}" for k in keys if d[k] is not None)
        )


def run(args: argparse.Namespace) -> int:
    _output.check([args.json], force=args.force)
    rec, calib, bf = _analysis_inputs.load(args)
    res = iso_of(rec, bf)
    print_table(res)
    _analysis_inputs.write_json(args.json, res.to_json())
    return report_missing(res)


def missing_characteristics(res) -> list[str]:
    """The key characteristics ISO 9283 could not give here (AP/RP, AT/RT NaN or absent)."""
    out = []
    if not res.poses and not res.paths:
        out.append("no test pose and no test path found in the measured poses")
    for p in res.poses:
        if not (np.isfinite(p.AP) and np.isfinite(p.RP)):
            out.append(f"pose {p.name}: AP/RP not defined ({p.n_cycles} cycles measured)")
    for path in res.paths:
        if not (np.isfinite(path.AT) and np.isfinite(path.RT)):
            out.append(f"path {path.name}: AT/RT not defined ({path.n_cycles} cycles measured)")
    return out


def report_missing(res) -> int:
    """A warning on stderr per missing characteristic; exit code 1 if any, else 0."""
    import sys

    missing = missing_characteristics(res)
    for m in missing:
        print(f"robtraj: warning: {m}", file=sys.stderr)
    return 1 if missing else 0
