"""`robtraj export CALIB.json --format urdf|json -o OUT`: a calibration for the cell's tools."""

from __future__ import annotations

import argparse
import json

import numpy as np

from .._errors import UserError
from . import _output


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "export",
        help="the calibrated robot as URDF, or every parameter with its σ as JSON",
        description=(
            "Write a calibration for the tools a cell already uses. urdf: the robot with "
            "the calibrated geometry in its joint origins (joint offsets, link lengths and "
            "twists) and the calibrated TCP as link 'tool'; what a URDF cannot hold "
            "(compliance, backlash, maps, ...) is listed in the file and printed. json: "
            "every parameter with its standard deviation, the maps' knots included."
        ),
    )
    p.add_argument("calibration", metavar="CALIB.json", help="from `robtraj calibrate`")
    p.add_argument("--format", required=True, choices=["urdf", "json"], help="what to write")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="file to write")
    p.add_argument(
        "--robot",
        metavar="MODEL",
        help="the robot calibrated (built-in name, DH JSON, URDF), for a CALIB.json that "
        "does not name it (made before robtraj stored it)",
    )
    p.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.export import calibration_urdf, not_representable, parameter_document
    from ..calibration_file import load_calibration
    from ._analysis_inputs import calibrated_robot

    _output.check([args.out], force=args.force)
    calib = load_calibration(args.calibration)
    if args.format == "json":
        _output.write_text(args.out, json.dumps(parameter_document(calib), indent=1))
        print(f"wrote {args.out}: {len(calib.parameter_names)} parameters with their σ")
        return 0
    robot = calibrated_robot(calib, args.robot, args.calibration)
    for name in ("joint_offset", "link_length", "link_twist"):
        value = calib.effects.get(name)
        if value is not None and np.shape(value)[0] != robot.n_joints:
            raise UserError(
                f"the calibration's {name} has {np.shape(value)[0]} joints, the robot "
                f"{robot.n_joints}"
            )
    _output.write_text(args.out, calibration_urdf(calib, robot))
    missing = not_representable(calib)
    print(
        f"wrote {args.out}: {robot.n_joints} joints, calibrated geometry and TCP"
        + (f"; not representable in URDF: {', '.join(missing)}" if missing else "")
    )
    return 0
