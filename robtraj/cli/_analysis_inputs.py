"""Shared by `iso9283`, `deviation` and `report`: recording + calibration → base-frame poses.

Inputs are checked before any computation: the output paths (`_output.check`), the
calibration through the one CALIB.json loader, the recording. After the poses, the
calibration is checked against the recording (`check_same_setup`).
"""

from __future__ import annotations

import argparse

import numpy as np

from .._errors import UserError
from . import _output

#: a calibration whose tool positions miss the recording's by more than this many times its
#: own residual RMS (and by more than `SETUP_FLOOR_M`) belongs to another setup
SETUP_FACTOR = 20.0
SETUP_FLOOR_M = 1e-3
_SETUP_FRAMES = 2000  # frames compared (evenly spaced), enough for a robust median


def calibrated_robot(calib, robot: str | None, calib_name: str):
    """The robot model `calib` calibrated: `robot` (a built-in name, DH JSON or URDF) if
    given, else the one CALIB.json names; `UserError` where neither is known."""
    from ..importers import read_robot_model, robot_description

    if robot is not None:
        return read_robot_model(robot).robot_model()
    if not calib.robot:
        raise UserError(f"{calib_name} does not name its robot (an older CALIB.json); give --robot")
    return robot_description(calib.robot, f"{calib_name}: robot").robot_model()


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
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")


def load(args: argparse.Namespace, *, need_program: bool = True):
    """(recording, calibration, base-frame poses) for an analysis command. The recording
    is read by frame ranges (`robtraj.open_recording`): the LED positions stay on disk,
    and are not readable from the returned recording; everything else is in memory."""
    from .._recording_reader import open_recording
    from ..calibration_file import load_calibration

    calib = load_calibration(args.calibration) if args.calibration else None
    with open_recording(args.recording, truth=False) as rec:
        if need_program and rec.program is None:
            raise UserError(
                f"{args.recording}: no /program (the commanded targets) to compare with"
            )
        calib, bf = _calibrated_poses(rec, calib, args)
    name = str(args.calibration or "the calibration")
    warn_undetermined(calib, name, "the result depends")
    args.warnings = warn_outside_maps(calib, frame_joints(rec), name)
    return rec, calib, bf


def _calibrated_poses(rec, calib, args: argparse.Namespace):
    """The calibration (`calib`, or one of `rec` itself when None) checked against `rec`,
    and the base-frame poses of `rec` under it."""
    from ..calibration_file import check_robot
    from ..estimate import base_frame_poses

    if calib is None:
        from ..estimate.calibration import fit

        calib = fit(rec, per_observation=False)
    check_robot(calib, rec, str(args.calibration))
    if not np.isin(rec.led_ids, np.asarray(calib.led_ids)).sum() >= 3:
        raise UserError(
            f"{args.recording}: fewer than 3 of its LEDs are in the calibration's constellation "
            "(a calibration of another tool?)"
        )
    bf = base_frame_poses(rec, calib, weighting=args.weighting)
    if not np.any(bf.valid):
        raise UserError(f"{args.recording}: no frame has a tool pose with this calibration")
    check_same_setup(rec, calib, bf, args.recording)
    return calib, bf


def frame_joints(rec) -> np.ndarray:
    """The logged joint angles `(N, joints)` [rad] (none without a robot log)."""
    return np.zeros((0, 0)) if rec.robot is None else np.asarray(rec.robot.joints, float)


def warn_outside_maps(calib, joints, name: str, rows: str = "frames") -> list[dict]:
    """A warning line on stderr when `joints` `(N, joints)` [rad] reach angles where a
    joint angle error map of `calib` was not fitted (it predicts its prior mean, zero,
    there); returns the warnings for the JSON output (`outside_maps`)."""
    import sys

    from ..analysis import outside_maps

    out = outside_maps(calib, joints)
    if out:
        parts = ", ".join(
            f"joint {w['joint']} in {100 * w['fraction']:.1f} % of the {rows}"
            + (
                ""
                if not w.get("fitted_range_rad")
                else " (fitted on {:.2f} to {:.2f} rad)".format(*w["fitted_range_rad"])
            )
            for w in out
        )
        print(
            f"robtraj: warning: {name}'s joint angle error maps were not fitted where the "
            f"joints are here: {parts}; there the maps predict no error (their prior mean)",
            file=sys.stderr,
        )
    return [{"kind": "joint_map_outside_fitted_range", "rows": rows, **w} for w in out]


def undetermined_rigid(calib) -> list[str]:
    """camera←base and flange←tool parameters that `calib`'s recording did not determine."""
    names = (getattr(calib, "identifiability", None) or {}).get("undetermined", [])
    return [n for n in names if n.startswith(("camera_from_base.", "flange_from_tool."))]


def weak_rigid(calib) -> list[dict]:
    """camera←base and flange←tool parameters determined only to a σ above the
    calibration's stated tolerance (``identifiability.weak``)."""
    weak = (getattr(calib, "identifiability", None) or {}).get("weak", [])
    return [w for w in weak if isinstance(w, dict) and "parameter" in w]


def _sigma_text(w: dict) -> str:
    unit, k = ("µm", 1e6) if ".t" in w["parameter"] else ("µrad", 1e6)
    return (
        f"{w['parameter']} σ {w['sigma'] * k:.0f} {unit} (tolerance {w['tolerance'] * k:.0f} "
        f"{unit})"
    )


def warn_undetermined(calib, name: str, consequence: str, refitted: tuple[str, ...] = ()) -> None:
    """Warning lines on stderr when `calib` leaves a rigid transform undetermined, or
    determines one only poorly (σ above its tolerance); transforms in `refitted`
    (``camera_from_base``, ``flange_from_tool``) are estimated anew and left out."""
    import sys

    def kept(parameter: str) -> bool:
        return parameter.split(".", 1)[0] not in refitted

    fix = (
        "calibrate on a run with reorientations about two axes (`robtraj calibrate` lists "
        "the poses to add)"
    )
    bad = [b for b in undetermined_rigid(calib) if kept(b)]
    if bad:
        print(
            f"robtraj: warning: {name} does not determine {', '.join(bad)} (the recording it "
            f"came from cannot tell them apart); {consequence} on them by an unknown amount: "
            + fix,
            file=sys.stderr,
        )
    weak = [w for w in weak_rigid(calib) if kept(w["parameter"])]
    if weak:
        print(
            f"robtraj: warning: {name} determines {', '.join(map(_sigma_text, weak))} only "
            f"poorly; {consequence} on them by about that much: " + fix,
            file=sys.stderr,
        )


def setup_discrepancy(rec, calib, bf) -> float | None:
    """Median distance [m] between the tool positions measured in `bf` (camera frame) and
    those the calibration predicts from the robot log; None without a robot log."""
    from ..analysis.prediction import predicted_tool_poses

    if rec.robot is None or rec.robot.joints.shape[0] < 2:
        return None
    frames = np.flatnonzero(bf.valid)
    frames = frames[np.linspace(0, frames.size - 1, min(frames.size, _SETUP_FRAMES)).astype(int)]
    predicted = predicted_tool_poses(rec, calib, np.asarray(rec.time, float)[frames])
    measured = np.asarray(bf.poses.position)[frames]
    d = np.linalg.norm(np.asarray(predicted.translation()) - measured, axis=1)
    return float(np.nanmedian(d))


def check_same_setup(rec, calib, bf, name: str) -> None:
    """Refuse a calibration whose predicted tool positions miss the recording's far beyond
    its own residual RMS: it comes from another setup (camera moved, other tool or robot)."""
    d = setup_discrepancy(rec, calib, bf)
    own = calib.residual_rms_m if np.isfinite(calib.residual_rms_m) else 0.0
    limit = max(SETUP_FACTOR * own, SETUP_FLOOR_M)
    if d is not None and d > limit:
        raise UserError(
            f"{name}: the calibration does not fit this recording: its tool positions are "
            f"{d * 1e3:.1f} mm (median) from those the robot log predicts, against the "
            f"calibration's own residual RMS of {own * 1e6:.0f} µm; it belongs to another setup "
            "(camera moved, other tool or robot): calibrate this setup (`robtraj calibrate`)"
        )


def write_json(path: str | None, doc: dict, warnings: list[dict] | None = None) -> None:
    """`doc` to `path` with the command's `warnings` (`warn_outside_maps`) added, if any."""
    _output.write_json(path, {**doc, "warnings": warnings} if warnings else doc)
