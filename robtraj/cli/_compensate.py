"""`robtraj compensate PROGRAM --calibration CALIB.json -o CORRECTED`: a program corrected
with the calibrated model."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from .._errors import UserError
from . import _output


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "compensate",
        help="correct a program's targets with the calibrated model",
        description=(
            "For each target, the joint angles at which the calibrated model (every "
            "effect: geometry, compliance, backlash, maps) puts the calibrated TCP on it, "
            "and the Cartesian command the controller's nominal model turns into those "
            "joints. PROGRAM: a recording (its /program, robot, nominal TCP and first "
            "joint angles) or a program CSV/JSON with --tool and --start-joints. Writes "
            "the commands as a program CSV (docs/campaign.md). A target out of reach, or "
            "whose nominal or compensated joints leave the robot's joint limits, is "
            "refused by name."
        ),
    )
    p.add_argument("program", metavar="PROGRAM", help="recording (.h5) or program CSV/JSON")
    p.add_argument("--calibration", required=True, metavar="CALIB.json")
    p.add_argument("-o", "--out", required=True, metavar="CORRECTED.csv", help="file to write")
    p.add_argument("--robot", metavar="MODEL", help="robot model, if CALIB.json names none")
    p.add_argument("--tool", metavar="TOOL", help="program file: the controller's TCP (tool file)")
    p.add_argument(
        "--start-joints",
        metavar="DEG,...",
        help="program file: joint angles [°] near the first target (the robot's branch)",
    )
    p.add_argument(
        "--tcp",
        choices=["nominal", "calibrated"],
        default="nominal",
        help="put on the targets: the controller's TCP carried by the calibrated flange "
        "(default; what iso9283 and deviation judge), or the calibrated tool frame (the "
        "tool mount corrected too)",
    )
    p.add_argument("--json", metavar="PATH", help="also write joints and predicted errors")
    p.add_argument("--force", action="store_true", help="overwrite outputs that exist")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.compensation import compensate
    from ..calibration_file import load_calibration
    from ..importers import program_csv
    from ._analysis_inputs import warn_outside_maps

    _output.check([args.out, args.json], force=args.force)
    calib = load_calibration(args.calibration)
    program, labels, robot, tcp, q_start = _inputs(args, calib)
    res = compensate(program, robot, calib, tcp, q_start, tcp=args.tcp, names=labels)
    warnings = warn_outside_maps(calib, res.joints, args.calibration, "targets")
    corrected = dataclasses.replace(program, targets=res.commands, segment=None)
    _output.write_text(args.out, program_csv(corrected, np.asarray(labels)))
    print(
        f"wrote {args.out}: {len(res.joints)} targets; the calibrated model puts the TCP "
        f"{res.error_before_m.mean() * 1e3:.3f} mm (max {res.error_before_m.max() * 1e3:.3f} "
        f"mm) from the targets uncompensated, {res.error_after_m.max() * 1e6:.2g} µm "
        "compensated (predicted; the calibration's own error comes on top)"
    )
    if args.json:
        doc = {
            "labels": labels,
            "joints_rad": res.joints.tolist(),
            "nominal_joints_rad": res.nominal_joints.tolist(),
            "predicted_error_uncompensated_m": res.error_before_m.tolist(),
            "predicted_error_compensated_m": res.error_after_m.tolist(),
            "warnings": warnings,
        }
        _output.write_text(args.json, json.dumps(doc, indent=1))
    return 0


def _inputs(args, calib):
    """(program, labels, robot model, controller's TCP, first joints) from PROGRAM."""
    from ..calibration_file import check_robot_model
    from ..importers import load_constellation, read_program
    from ..model import robot_from_log
    from ..recording import read_recording
    from ._analysis_inputs import calibrated_robot

    path = Path(args.program)
    if path.suffix.lower() in (".h5", ".hdf5"):
        rec = read_recording(path)
        if rec.program is None or rec.robot is None or rec.tool is None:
            raise UserError(f"{path}: needs /program, /robot and /tool to be compensated")
        program, labels = rec.program, _labels(rec.extras.get("program/label"), rec.program)
        tcp = rec.tool.flange_from_tool
        robot = robot_from_log(rec.robot)
        q_start = np.asarray(rec.robot.joints[0])
    else:
        program, extra = read_program(path)
        labels = _labels(extra.get("label"), program)
        if args.tool is None or args.start_joints is None:
            raise UserError("a program file needs --tool (the controller's TCP) and --start-joints")
        tcp = load_constellation(args.tool).flange_from_tool
        if tcp is None:
            raise UserError(f"{args.tool}: the tool file has no flange_from_tool (the TCP)")
        try:
            q_start = np.deg2rad([float(v) for v in args.start_joints.split(",")])
        except ValueError:
            raise UserError(
                f"--start-joints must be numbers [°], not {args.start_joints!r}"
            ) from None
        robot = calibrated_robot(calib, args.robot, args.calibration)
    if tcp is None:
        raise UserError(f"{path}: the tool has no nominal flange_from_tool (the controller's TCP)")
    if np.shape(q_start) != (robot.n_joints,):
        raise UserError(f"--start-joints needs {robot.n_joints} angles, got {np.size(q_start)}")
    if args.robot is None:
        check_robot_model(calib, robot, args.calibration)
    return program, labels, robot, tcp, q_start


def _labels(values, program) -> list[str]:
    n = len(program.motion)
    return [str(v) for v in values] if values is not None and len(values) == n else [""] * n
