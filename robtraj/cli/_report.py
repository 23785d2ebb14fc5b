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


def _inputs(rec, args: argparse.Namespace, notes: list[str]):
    """(calibration or None, base-frame poses or None): what can be had from the
    recording `rec`; what cannot goes to `notes`."""
    from ..calibration_file import check_robot, load_calibration
    from ..estimate import base_frame_poses

    calib = None
    args.warnings = []
    if args.calibration:
        calib = load_calibration(args.calibration)
        check_robot(calib, rec, args.calibration)
        joints = _analysis_inputs.frame_joints(rec)
        args.warnings = _analysis_inputs.warn_outside_maps(calib, joints, args.calibration)
        notes += [
            f"the calibration's joint {w['joint']} angle error map was not fitted at "
            f"{100 * w['fraction']:.1f} % of the frames (it predicts no error there)"
            for w in args.warnings
        ]
    elif rec.robot is None or rec.tool is None:
        missing = " and ".join(
            w for w, x in [("robot log", rec.robot), ("tool constellation", rec.tool)] if x is None
        )
        notes.append(f"no calibration: the recording has no {missing} (give --calibration)")
    else:
        from ..estimate.calibration import fit

        try:
            calib = fit(rec, per_observation=False)
        except UserError as e:
            notes.append(f"no calibration: self-calibration of the recording failed: {e}")
    bf = None
    if calib is not None:
        bf = base_frame_poses(rec, calib, weighting=args.weighting)
        if args.calibration:
            _analysis_inputs.check_same_setup(rec, calib, bf, args.recording)
    if rec.program is None:
        notes.append("ISO 9283 and path deviation left out: no program (/program)")
    elif bf is None:
        notes.append(
            "ISO 9283 and path deviation left out: no calibration, so no poses in the robot "
            "base frame"
        )
    return calib, bf


def _analyses(rec, bf, notes: list[str]):
    """(reference path, deviation, ISO 9283 result), each None where it cannot be had
    (the reason to `notes`). ISO 9283 first: its passes' temporaries and the deviation's
    per-frame result are then never in memory together."""
    from ._deviation import deviation_of
    from ._iso9283 import iso_of, missing_characteristics

    if rec.program is None or bf is None:
        return None, None, None
    iso_notes: list[str] = []
    try:
        iso = iso_of(rec, bf)
        iso_notes += [f"ISO 9283: {m}" for m in missing_characteristics(iso)]
    except UserError as e:
        iso = None
        iso_notes.append(f"ISO 9283 left out: {e}")
    try:
        ref, dev = deviation_of(rec, bf)
        dev.summary()  # raises when no frame lies on a linear move
    except UserError as e:
        ref = dev = None
        notes.append(f"path deviation left out: {e}")
    notes += iso_notes
    return ref, dev, iso


def run(args: argparse.Namespace) -> int:
    from .._recording_reader import open_recording
    from ..analysis import write_tum
    from ..report import recording_parts, recording_report

    out = Path(args.out)
    _output.check([args.json], [out], force=args.force)
    notes: list[str] = []
    # the LED positions stay on disk: every pass over them reads them chunk by chunk
    with open_recording(args.recording, truth=False) as rec, _output.new_folder(out) as tmp:
        calib, bf = _inputs(rec, args, notes)
        own = recording_parts(tmp, rec, bf)  # before the analyses' per-frame results
        ref, dev, iso = _analyses(rec, bf, notes)
        path = recording_report(
            tmp,
            rec,
            calib,
            bf,
            deviation=dev,
            reference=ref,
            iso=iso,
            name=Path(args.recording).name,
            notes=notes,
            own=own,
        )
        if bf is not None:
            v = bf.valid
            write_tum(tmp / "measured.tum", bf.time, bf.position, bf.quaternion_wxyz, v)
            if dev is not None:
                foot, foot_q = dev.foot, dev.foot_quaternion_wxyz
                write_tum(tmp / "commanded.tum", bf.time, foot, foot_q, v)
    path = out / path.relative_to(tmp)
    _analysis_inputs.write_json(
        args.json,
        {
            "report": str(path),
            "iso9283": None if iso is None else iso.to_json(),
            "deviation": None if dev is None else dev.summary().to_json(),
            "notes": notes,
        },
        args.warnings,
    )
    for n in notes:
        print(f"note: {n}")
    print(f"report: {path}")
    return 0
