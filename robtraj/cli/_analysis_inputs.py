"""Shared by `iso9283`, `deviation` and `report`: recording + calibration → base-frame poses."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .._errors import UserError


def add_arguments(p: argparse.ArgumentParser, *, calibration_required: bool = True) -> None:
    p.add_argument("recording", metavar="REC.h5", help="recording with /program")
    p.add_argument(
        "--calibration",
        required=calibration_required,
        metavar="CALIB.json",
        help="from `robtraj calibrate`"
        + ("" if calibration_required else " (default: calibrate this recording first)"),
    )
    p.add_argument("--weighting", default="led_noise", help="LED weighting for the poses")
    p.add_argument("--json", metavar="PATH", help="write the machine-readable result")


def load(args: argparse.Namespace):
    """(recording, calibration, base-frame poses) for an analysis command."""
    from ..estimate._base_frame import base_frame_poses, load_calibration
    from ..recording import read_recording

    rec = read_recording(args.recording)
    if rec.program is None:
        raise UserError(f"{args.recording}: no /program (the commanded targets) to compare with")
    if args.calibration:
        calib = load_calibration(args.calibration)
    else:
        from ..estimate.calibration import fit

        calib = fit(rec)
    return rec, calib, base_frame_poses(rec, calib, weighting=args.weighting)


def write_json(path: str | None, doc: dict) -> None:
    if path:
        Path(path).write_text(json.dumps(doc, indent=2, allow_nan=False))
