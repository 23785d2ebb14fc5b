"""How well a calibration predicts another recording of the same robot and tool.

The calibration's model (its effects and LED constellation) is held; only the rigid
transforms that differ between campaigns are refitted on the other recording (by default
camera←base: the tracker stood elsewhere; optionally flange←tool: the tool was mounted
again). The tool pose the model then predicts from the robot log is compared, frame by
frame, with the measured one: the probe pose of a 6-DOF tracker (`robtraj import --format
pose-csv`: every frame probed) or else the per-frame fit of the LEDs with the
calibration's constellation. LEDs the calibration never saw are left out (their
positions are nominal, not measured).

Errors: position of the tool origin [m] (camera frame, ``|t_measured − t_predicted|``)
and orientation [rad] (angle of ``R_measuredᵀ R_predicted``). The gap is the position
RMS with the tracker noise taken out (DESIGN section 7), where the recording reports that
noise (`/tracker/pose_std`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Float

from .._errors import UserError
from ..calibration_file import check_robot
from ..estimate import base_frame_poses
from ..estimate.calibration import CalibrationResult, fit
from ..model import (
    interpolate_joints,
    motion_direction,
    motion_sign,
    pose_se3,
    predict_tool_poses,
    robot_from_log,
)
from ..recording import Recording
from ._named_model import pose_prediction, pose_representable
from ._pose_fit import error_summary
from ._pose_series import is_ur10

#: the rigid transforms a prediction may refit
RIGID = ("camera_from_base", "flange_from_tool")


@dataclasses.dataclass(frozen=True)
class Prediction:
    """Per frame of the evaluated recording (NaN where no measured pose): `position_error`
    [m], `angle_error` [rad], `tool_position` `(N, 3)` the measured tool origin in the base
    frame [m]; `calibration` the calibration with the refitted transforms; `refit` what was
    refitted; `measured_by` ``"probe"`` or ``"leds"``; `noise_m` the tracker's per-axis
    position noise [m] (None where the recording does not report it)."""

    time: Float[np.ndarray, " n"]
    position_error: Float[np.ndarray, " n"]
    angle_error: Float[np.ndarray, " n"]
    tool_position: Float[np.ndarray, "n 3"]
    calibration: CalibrationResult
    refit: tuple[str, ...]
    measured_by: str
    noise_m: float | None

    def summary(self) -> dict[str, Any]:
        """mean / RMS / max position error [mm], mean / max orientation error [deg], the
        gap [mm] (None without a noise figure) and the number of poses compared."""
        ok = np.isfinite(self.position_error) & np.isfinite(self.angle_error)
        out: dict[str, Any] = error_summary(
            self.position_error[ok], self.angle_error[ok], self.noise_m or 0.0
        )
        if self.noise_m is None:
            out["gap_mm"] = None
        out["poses"] = int(ok.sum())
        return out

    def to_json(self) -> dict[str, Any]:
        def listed(a):
            return [None if not np.isfinite(x) else float(x) for x in np.ravel(a)]

        calib = self.calibration.to_json()
        return {
            "summary": self.summary(),
            "refit": list(self.refit),
            "measured_by": self.measured_by,
            "noise_m": self.noise_m,
            "camera_from_base": calib["camera_from_base"],
            "flange_from_tool": calib["flange_from_tool"],
            "converged": self.calibration.converged,
            "per_pose": {
                "time_s": self.time.tolist(),
                "position_error_m": listed(self.position_error),
                "angle_error_rad": listed(self.angle_error),
            },
        }


def predicted_tool_poses(rec: Recording, calib, time: np.ndarray) -> jaxlie.SE3:
    """camera←tool that `calib` predicts from `rec`'s robot log at tracker times `time` [s]
    (its clock offset, effects and drift variable applied)."""
    robot, q, direction, drift, moving = model_inputs(rec, calib, time)
    return predict_tool_poses(
        robot,
        calib.effects_module(rec.robot.joints.shape[1]),
        pose_se3(calib.camera_from_base),
        pose_se3(calib.flange_from_tool),
        q,
        direction,
        drift,
        moving,
    )


def model_inputs(rec: Recording, calib, time: np.ndarray) -> tuple:
    """What the forward model (`predict_tool_poses`) takes besides the parameters, at
    tracker times `time` [s]: the robot, the joints at ``time + τ``, their direction and
    motion sign, and the drift variable (K since the first frame, else minutes)."""
    robot = robot_from_log(rec.robot)
    t = np.asarray(time, float) + calib.time_offset
    log_t, joints = np.asarray(rec.robot.time, float), np.asarray(rec.robot.joints, float)
    q = interpolate_joints(jnp.asarray(log_t), jnp.asarray(joints), jnp.asarray(t))
    direction = motion_direction(log_t, joints, t)
    frames = np.clip(np.searchsorted(np.asarray(rec.time, float), time), 0, rec.time.size - 1)
    if rec.temperature is not None:
        drift = np.asarray(rec.temperature, float)[frames] - float(rec.temperature[0])
    else:
        drift = (np.asarray(time, float) - float(rec.time[0])) / 60.0
    moving = motion_sign(log_t, joints, t, calib.motion_threshold)
    return (
        robot,
        q,
        jnp.asarray(direction),
        jnp.asarray(np.nan_to_num(drift)),
        jnp.asarray(moving),
    )


def _check(rec: Recording, calib: CalibrationResult) -> None:
    if rec.robot is None or rec.robot.joints.shape[0] < 2:
        raise UserError("the recording has no robot log (/robot/joints): nothing to predict from")
    check_robot(calib, rec)
    n = rec.robot.joints.shape[1]
    sizes = {k: np.size(v) for k, v in calib.effects.items() if k != "time_offset"}
    per_joint = {
        "joint_offset": n,
        "joint_compliance": n,
        "backlash": n,
        "link_length": 2 * n,
        "link_twist": 2 * n,
    }
    wrong = [k for k, size in per_joint.items() if k in sizes and sizes[k] != size]
    if wrong:
        raise UserError(
            f"the calibration's {', '.join(wrong)} do not fit a robot of {n} joints: a "
            "calibration of another robot model"
        )
    if rec.tool is None or np.isin(rec.tool.led_ids, calib.led_ids).sum() < 3:
        raise UserError(
            "fewer than 3 of the recording's tool LEDs are in the calibration's constellation "
            "(a calibration of another tool?)"
        )


def predict(
    rec: Recording,
    calibration: CalibrationResult,
    refit: Sequence[str] = ("camera_from_base",),
    *,
    progress=None,
) -> Prediction:
    """The prediction error of `calibration` on `rec` with only `refit` (any of `RIGID`)
    refitted (module docstring). Raises `UserError` for a recording without robot log or
    a calibration of another robot or tool."""
    refit = tuple(dict.fromkeys(refit))
    bad = [r for r in refit if r not in RIGID]
    if bad:
        raise UserError(f"cannot refit {', '.join(bad)} (choose from {', '.join(RIGID)})")
    _check(rec, calibration)
    unknown = np.isin(rec.led_ids, np.asarray(calibration.unseen_leds, int))
    if unknown.any():  # LEDs the calibration never saw: their positions are not known
        rec = rec.replace(positions=np.where(unknown[None, :, None], np.nan, rec.positions))
    if _probed(rec) and pose_representable(calibration) and is_ur10(rec):
        return _probe_prediction(rec, calibration, refit)
    hold = tuple(g for g in (*RIGID, "constellation") if g not in refit)
    calib = fit(rec, init=calibration, hold=hold, progress=progress)
    if _probed(rec):
        time = np.asarray(rec.probe.time, float)
        measured = _wxyz_xyz(rec.probe.tool_pose)
        by = "probe"
    else:
        est = base_frame_poses(rec, calib).poses
        ok = np.asarray(est.valid, bool)
        time = np.asarray(est.time, float)[ok]
        measured = np.concatenate([est.quaternion_wxyz[ok], est.position[ok]], -1)
        by = "leds"
    pred = predicted_tool_poses(rec, calib, time)
    meas = jaxlie.SE3(jnp.asarray(measured))
    delta = meas.inverse() @ pred
    pos = np.linalg.norm(np.asarray(pred.translation()) - measured[:, 4:], axis=-1)
    ang = np.linalg.norm(np.asarray(delta.rotation().log()), axis=-1)
    tool_in_base = np.asarray(pose_se3(calib.camera_from_base).inverse().apply(meas.translation()))
    return Prediction(
        time=time,
        position_error=pos,
        angle_error=ang,
        tool_position=tool_in_base,
        calibration=calib,
        refit=refit,
        measured_by=by,
        noise_m=_tracker_noise(rec),
    )


def _probed(rec: Recording) -> bool:
    """Whether every frame of `rec` has a 6-DOF probe pose."""
    return rec.probe is not None and len(rec.probe.time) == rec.time.size


def _wxyz_xyz(pose) -> np.ndarray:
    return np.concatenate([np.asarray(pose.quaternion_wxyz), np.asarray(pose.position)], -1)


def _tracker_noise(rec: Recording) -> float | None:
    """The tracker's per-axis position noise [m] from `/tracker/pose_std`, if reported."""
    std = (rec.extras or {}).get("tracker/pose_std")
    return float(np.sqrt(np.mean(np.asarray(std)[:, :3] ** 2))) if std is not None else None


def _probe_prediction(
    rec: Recording, calibration: CalibrationResult, refit: tuple[str, ...]
) -> Prediction:
    """The prediction of a 6-DOF probe recording by its pose residual
    (`_named_model.pose_prediction`)."""
    fit6, calib = pose_prediction(rec, calibration, refit)
    measured = _wxyz_xyz(rec.probe.tool_pose)
    z = pose_se3(calib.camera_from_base)
    return Prediction(
        time=np.asarray(rec.probe.time, float),
        position_error=fit6.position_error,
        angle_error=fit6.angle_error,
        tool_position=np.asarray(z.inverse().apply(jnp.asarray(measured[:, 4:]))),
        calibration=calib,
        refit=refit,
        measured_by="probe",
        noise_m=_tracker_noise(rec),
    )
