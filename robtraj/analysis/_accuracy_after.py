"""Accuracy after compensation, predicted from a recording and its calibration.

Per ISO 9283 test pose: the error measured now, ``AP_xyz`` = barycentre of the attained
positions of the controller's TCP − command (base frame, m), and the error predicted
once the program is compensated with the calibration (`compensate`). The controller
turns the command T into joints q_T (nominal inverse kinematics) and reaches them up
to its own positioning error e, so ``AP_now = R(q_T + e) − T``; compensated, the
calibrated model M reaches T itself, and what remains is
``AP_after = AP_now − (M(q_T) − T)``: the correction the model predicts at the command,
subtracted from the error measured. What M does not describe, and the controller's e,
stay. Here ``AP_after`` is the barycentre of ``attained − M(q_T)`` over the pose's
attainments (M with every effect, backlash by each attainment's approach direction).

Its σ is the calibration's: the covariance of camera←base, flange←tool and the effects,
with each σ the one the calibration quotes (`CalibrationResult.quoted`: the largest of
Gauss–Newton, cluster-robust and model-error field; Gauss–Newton's correlations), carried linearly to ``AP_after`` by JAX forward-mode
(camera←base and flange←tool move the measured positions, the effects the model). The
maps' knots carry no covariance in CALIB.json and are left out of σ; the scatter of the
attainments (repeatability) is not a model error and is not in it either.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Float

from ..model import (
    Effects,
    effect_component_names,
    inverse_kinematics,
    pose_se3,
    predict_tool_poses,
)
from ..recording import Recording
from .iso9283 import Iso9283Result
from .prediction import model_inputs

_TANGENT = ("tx", "ty", "tz", "rx", "ry", "rz")


@dataclasses.dataclass(frozen=True)
class AccuracyAfterCompensation:
    """Per ISO test pose (`names`): `error_now` `(P, 3)` [m] the measured AP vector,
    `error_after` `(P, 3)` [m] the AP vector predicted after compensation, `sigma_after`
    `(P,)` [m] its 1σ per axis (RMS over the axes) from the calibration's uncertainty
    (NaN where the calibration has no covariance)."""

    names: list[str]
    error_now: Float[np.ndarray, "poses 3"]
    error_after: Float[np.ndarray, "poses 3"]
    sigma_after: Float[np.ndarray, " poses"]

    def to_json(self) -> dict[str, Any]:
        return {
            n: {
                "AP_now_mm": float(np.linalg.norm(a) * 1e3),
                "AP_after_predicted_mm": float(np.linalg.norm(b) * 1e3),
                "sigma_after_mm": float(s * 1e3),
            }
            for n, a, b, s in zip(self.names, self.error_now, self.error_after, self.sigma_after)
        }


def accuracy_after_compensation(
    rec: Recording, calib, iso: Iso9283Result
) -> AccuracyAfterCompensation | None:
    """`AccuracyAfterCompensation` of the ISO pose test `iso` measured in `rec` with
    calibration `calib` (module docstring); None without pose characteristics."""
    poses = [p for p in iso.poses if p.n_cycles > 0]
    if not poses or rec.robot is None:
        return None
    time = np.concatenate([np.asarray(p.attained_time, float) for p in poses])
    owner = jnp.asarray(np.repeat(np.arange(len(poses)), [p.n_cycles for p in poses]))
    counts = np.array([p.n_cycles for p in poses], float)[:, None]
    attained = np.concatenate(
        [
            np.concatenate(
                [np.asarray(p.attained_quaternion_wxyz), np.asarray(p.attained_position)], -1
            )
            for p in poses
        ]
    )
    names, cov = _covariance(calib)
    measured = _measured(calib, rec, names, attained)
    robot, q, direction, drift, moving = model_inputs(rec, calib, time)
    q_target = _target_joints(robot, rec, calib, poses, np.asarray(q), np.asarray(owner))
    inputs = (robot, jnp.asarray(q_target)[owner], direction, drift, jnp.zeros_like(moving))
    model = _model(calib, rec, names, inputs)

    def error(delta):  # (P, 3): barycentre of measured − model per pose
        d = measured(delta) - model(delta)
        return jax.ops.segment_sum(d, owner, len(poses)) / counts

    zero = jnp.zeros(len(names))
    if names:
        jac = np.asarray(jax.jacfwd(error)(zero)).reshape(len(poses), 3, len(names))
        var = np.einsum("pik,kl,pil->p", jac, cov, jac)
    else:  # a calibration without a covariance states no uncertainty
        var = np.full(len(poses), np.nan)
    return AccuracyAfterCompensation(
        names=[p.name for p in poses],
        error_now=np.stack([p.AP_xyz for p in poses]),
        error_after=np.asarray(error(zero)),
        sigma_after=np.sqrt(np.clip(var, 0, None) / 3.0),
    )


def _target_joints(robot, rec, calib, poses, q_logged, owner) -> np.ndarray:
    """`(P, J)` [rad]: the controller's joints for each pose's command (nominal inverse
    kinematics of the command's flange, from the mean logged joints there)."""
    tool = _nominal_tool(rec, calib)
    command = np.stack(
        [np.concatenate([p.commanded_quaternion_wxyz, p.commanded_position]) for p in poses]
    )
    flange = jaxlie.SE3(jnp.asarray(command)) @ tool.inverse()
    seed = np.stack([q_logged[owner == k].mean(0) for k in range(len(poses))])
    solve = jax.vmap(lambda f, q0: inverse_kinematics(robot, jaxlie.SE3(f), q0))
    return np.asarray(solve(flange.wxyz_xyz, jnp.asarray(seed)))


def _nominal_tool(rec: Recording, calib) -> jaxlie.SE3:
    """The TCP the controller knows (what ISO 9283 judges), else the calibrated tool."""
    tool = rec.tool.flange_from_tool if rec.tool is not None else None
    return pose_se3(tool if tool is not None else calib.flange_from_tool)


def _tangent(names: list[str], group: str):
    """δ ↦ the right tangent step `(6,)` of `group` (zero where not among `names`)."""
    pad = len(names)  # a zero appended to δ stands for the entries not among them
    index = np.array(
        [names.index(f"{group}.{t}") if f"{group}.{t}" in names else pad for t in _TANGENT]
    )

    def step(delta):
        return jnp.concatenate([delta, jnp.zeros(1, delta.dtype)])[index]

    return step


def _measured(calib, rec: Recording, names: list[str], attained: np.ndarray):
    """δ ↦ `(N, 3)` the attained TCP positions in the base frame [m] had camera←base
    and flange←tool been moved by δ: the measured tool frame is the calibrated one,
    carried to the controller's TCP by ``c = (flange←tool)⁻¹ · nominal TCP``."""
    poses = jaxlie.SE3(jnp.asarray(attained))
    c = pose_se3(calib.flange_from_tool).inverse() @ _nominal_tool(rec, calib)
    camera, tool = _tangent(names, "camera_from_base"), _tangent(names, "flange_from_tool")

    def fn(delta):
        right = c.inverse() @ jaxlie.SE3.exp(-tool(delta)) @ c
        moved = jax.vmap(
            lambda w: (jaxlie.SE3.exp(-camera(delta)) @ jaxlie.SE3(w) @ right).translation()
        )
        return moved(poses.wxyz_xyz)

    return fn


def _model(calib, rec: Recording, names: list[str], inputs):
    """δ ↦ `(N, 3)` the controller's TCP in the base frame [m] that the calibrated
    model puts at the logged joints, its effect entries moved by δ."""
    robot, q, direction, _drift, moving = inputs
    effects = calib.effects_module(robot.n_joints)
    tool = _nominal_tool(rec, calib)
    where = _entries(effects, names)

    def fn(delta):
        moved = effects
        for name, (columns, entries) in where.items():
            value = jnp.ravel(moved.get(name)).at[entries].add(delta[columns])
            moved = moved.replace(name, value.reshape(jnp.shape(effects.get(name))))
        poses = predict_tool_poses(
            robot, _static(moved), jaxlie.SE3.identity(), tool, q, direction,
            jnp.zeros(q.shape[0]), moving,
        )  # fmt: skip
        return poses.translation()

    return fn


def _static(effects: Effects) -> Effects:
    """`effects` without what acts on the camera (drift, scale): base-frame positions."""
    return effects.replace("thermal_drift", jnp.zeros(3)).replace("tracker_scale", jnp.zeros(()))


def _entries(effects: Effects, names: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per effect with parameters among `names`: their columns in `names` and their
    entries in the effect's flattened value."""
    out = {}
    fields = {n.partition("[")[0].partition(".")[0] for n in names}
    for field in fields:
        try:
            shape = np.shape(effects.get(field))
        except (KeyError, AttributeError):
            continue
        component = effect_component_names(field, shape)
        pairs = [(names.index(c), k) for k, c in enumerate(component) if c in names]
        if pairs:
            cols, entries = map(np.asarray, zip(*pairs))
            out[field] = (cols, entries)
    return out


def _covariance(calib) -> tuple[list[str], np.ndarray]:
    """Names of camera←base, flange←tool and the effect parameters with a covariance
    (not the maps' knots, not the constellation) and their covariance, scaled so each σ
    is the quoted one (`CalibrationResult.sigma`)."""
    names = [
        n
        for n in calib.parameter_names
        if not n.startswith("constellation") and "_map." not in n and n != "time_offset"
    ]
    idx = [calib.parameter_names.index(n) for n in names]
    cov = np.asarray(calib.covariance, float)[np.ix_(idx, idx)]
    quoted = np.array([calib.sigma.get(n, np.nan) for n in names])
    gn = np.sqrt(np.clip(np.diag(cov), 0, None))
    keep = np.isfinite(quoted) & (gn > 0)
    scale = quoted[keep] / gn[keep]
    kept = cov[np.ix_(keep, keep)] * np.outer(scale, scale)
    return [n for n, k in zip(names, keep) if k], kept
