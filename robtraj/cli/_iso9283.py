"""`robtraj iso9283`: the ISO 9283 performance characteristics."""

from __future__ import annotations

import argparse
import sys

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


ISO_CYCLES = 30  # the standard's number of cycles for pose and path characteristics
_UNITS = {"_mm_per_s": "mm/s", "_percent": "%", "_mm": "mm", "_deg": "°", "_s": "s"}


def print_table(res) -> None:
    """Each characteristic with its 95 % interval, block by block, with the cycles it
    rests on; warns (stderr) where a pose or path has fewer than the standard's 30."""
    doc = res.to_json()
    few = []
    for block, items in doc.items():
        for name, d in items.items():
            n = d.get("n_cycles", d.get("n"))
            print(f"{block[:-1]} {name}: {n} cycles")
            if n is not None and n < ISO_CYCLES:
                few.append(f"{name} ({n})")
            for key, value in d.items():
                if f"{key}_ci95" not in d:
                    continue
                suffix = next((k for k in _UNITS if key.endswith(k)), "")
                label, unit = key[: len(key) - len(suffix)], _UNITS.get(suffix, "")
                ci = d[f"{key}_ci95"]
                band = f"[{ci[0]:.4g}, {ci[1]:.4g}]" if ci is not None else "(no interval)"
                shown = "n/a" if value is None else f"{value:.4g}"
                print(f"  {label:<14} {shown:>11} {unit:<4} 95 % CI {band}")
    if few:
        print(
            f"robtraj: warning: fewer than the standard's {ISO_CYCLES} cycles: {', '.join(few)}; "
            "the characteristics and their intervals rest on these",
            file=sys.stderr,
        )


def run(args: argparse.Namespace) -> int:
    _output.check([args.json], force=args.force)
    rec, calib, bf = _analysis_inputs.load(args)
    res = iso_of(rec, bf)
    print_table(res)
    doc = {
        **res.to_json(),
        "calibration_undetermined": _analysis_inputs.undetermined_rigid(calib),
        "calibration_weak": _analysis_inputs.weak_rigid(calib),
    }
    _analysis_inputs.write_json(args.json, doc, args.warnings)
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
