"""`robtraj evaluate`: the prediction error of a calibration on another recording."""

from __future__ import annotations

import argparse

from .._errors import UserError
from . import _output
from ._analysis_inputs import warn_outside_maps, warn_undetermined

#: exit status when the refit of the rigid transforms did not converge
NOT_CONVERGED = 3
#: short names accepted by --refit
_ALIASES = {
    "camera": "camera_from_base",
    "camera_from_base": "camera_from_base",
    "tool": "flange_from_tool",
    "probe": "flange_from_tool",
    "flange_from_tool": "flange_from_tool",
}


def register(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "evaluate",
        help="prediction error of a calibration on another recording of the robot",
        description=(
            "Predict REC.h5 (a robot log with LED or 6-DOF probe measurements, e.g. from "
            "`robtraj import --preset ipa-ur10`) with CALIB.json's model (effects and LED "
            "constellation held), refitting only the rigid transforms that change between "
            "campaigns, and report the tool pose error per frame: mean/RMS/max position, "
            "mean/max orientation and the gap. Exit status: 0, 3 when the refit did not "
            "converge, 2 on bad input."
        ),
    )
    p.add_argument("recording", metavar="REC.h5", help="recording with robot log and tool")
    p.add_argument("--calibration", required=True, metavar="CALIB.json",
                   help="from `robtraj calibrate` on another recording")  # fmt: skip
    p.add_argument(
        "--refit",
        default="camera",
        metavar="LIST",
        help="rigid transforms refitted: camera (camera<-base, default), tool/probe "
        "(flange<-tool), comma-separated",
    )
    p.add_argument("--json", metavar="PATH", help="summary and per-pose errors")
    p.add_argument("--plot", metavar="PNG", help="figure of the errors over the workspace")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.prediction import predict
    from ..calibration_file import load_calibration
    from ..recording import read_recording

    names = [s.strip() for s in args.refit.split(",") if s.strip()]
    bad = [s for s in names if s not in _ALIASES]
    if bad or not names:
        raise UserError(
            f"--refit {args.refit!r}: choose from camera, tool (comma-separated)"
            if not bad
            else f"--refit: unknown {', '.join(bad)} (choose from camera, tool)"
        )
    _output.check([args.json, args.plot], force=args.force)
    calib = load_calibration(args.calibration)
    rec = read_recording(args.recording)
    refit = tuple(_ALIASES[s] for s in names)
    warn_undetermined(calib, args.calibration, "the prediction depends", refit)
    pred = predict(rec, calib, list(refit))
    rows = "poses" if pred.measured_by == "probe" else "frames"
    warnings = warn_outside_maps(calib, rec.robot.joints, args.calibration, rows)
    _output.write_json(args.json, {**pred.to_json(), "warnings": warnings})
    if args.plot:
        from ..report import workspace_error_figure

        with _output.new_file(args.plot) as tmp:
            workspace_error_figure(tmp, pred.tool_position, pred.position_error, pred.angle_error)
    s = pred.summary()
    gap = (
        "n/a (no tracker noise in the recording)"
        if s["gap_mm"] is None
        else f"{s['gap_mm']:.3f} mm"
    )
    print(
        f"{args.recording} predicted by {args.calibration} ({pred.measured_by}, {s['poses']} "
        f"poses; refitted {', '.join(pred.refit)}):\n"
        f"  position error mean {s['pos_mean_mm']:.3f} mm, RMS {s['pos_rms_mm']:.3f} mm, "
        f"max {s['pos_max_mm']:.3f} mm\n"
        f"  orientation error mean {s['ang_mean_deg']:.4f}°, max {s['ang_max_deg']:.4f}°\n"
        f"  gap {gap}"
    )
    if not pred.calibration.converged:
        print(f"NOT converged: {pred.calibration.convergence}")
        return NOT_CONVERGED
    return 0
