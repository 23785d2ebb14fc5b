"""`robtraj report`: the HTML report of a recording."""

from __future__ import annotations

import argparse
from pathlib import Path

from .._errors import UserError
from . import _analysis_inputs, _output


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "report",
        help="HTML report: ISO table, path, deviation, speed, LEDs, pose quality",
        description=(
            "Write DIR/report.html with legible PNGs, and measured/commanded trajectories in "
            "the TUM format (for evo). Without --calibration the recording calibrates itself."
        ),
    )
    _analysis_inputs.add_arguments(p, calibration_required=False)
    p.add_argument("--out", required=True, metavar="DIR")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis import write_tum
    from ..report._recording_report import recording_report
    from ._deviation import deviation_of
    from ._iso9283 import iso_of, missing_characteristics

    out = Path(args.out)
    _output.check([args.json], [out], force=args.force)
    rec, calib, bf = _analysis_inputs.load(args, need_program=False)
    ref = dev = iso = None
    notes = []
    if rec.program is None:
        notes.append("no /program in the recording: ISO 9283 and path deviation left out")
    else:
        try:
            ref, dev = deviation_of(rec, bf)
        except UserError as e:
            notes.append(f"path deviation skipped: {e}")
        try:
            iso = iso_of(rec, bf)
            notes += [f"ISO 9283: {m}" for m in missing_characteristics(iso)]
        except UserError as e:
            notes.append(f"ISO 9283 skipped: {e}")
    with _output.new_folder(out) as tmp:
        path = recording_report(
            tmp, rec, calib, bf, deviation=dev, reference=ref, iso=iso,
            name=Path(args.recording).name,
        )  # fmt: skip
        v = bf.valid
        write_tum(tmp / "measured.tum", bf.time[v], bf.position[v], bf.quaternion_wxyz[v])
        if dev is not None:
            write_tum(tmp / "commanded.tum", bf.time[v], dev.foot[v], dev.foot_quaternion_wxyz[v])
    path = out / path.relative_to(tmp)
    _analysis_inputs.write_json(
        args.json,
        {
            "report": str(path),
            "iso9283": None if iso is None else iso.to_json(),
            "deviation": None if dev is None else dev.summary().to_json(),
            "notes": notes,
        },
    )
    for n in notes:
        print(f"note: {n}")
    print(f"report: {path}")
    return 0
