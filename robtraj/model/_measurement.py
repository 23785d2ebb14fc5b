"""The one forward measurement model (DESIGN section 5, with the effects of section 7).

``y_tk = (1 + s) · camera_from_base(T) · flange(q(t + τ)) · flange_from_tool ·
(p_k + b(θ_tk) n_k)`` where the flange pose is the forward kinematics of the joint
log interpolated at robot time t + τ, with joint offsets, backlash, compliance,
link-length and link-twist errors applied.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from ._camera import emission_angle
from ._dictionary import joint_term_error, led_term_offset
from ._effects import BIAS_REFERENCE_ANGLE, Effects
from ._kinematics import RobotModel, forward_kinematics, gravity_torque


def interpolate_joints(
    log_time: Float[Array, " k"], joints: Float[Array, "k joints"], t: Float[Array, " n"]
) -> Float[Array, "n joints"]:
    """Joint angles at times `t` (robot clock) by C¹ cubic Hermite interpolation of the log.

    Slopes are central differences (one-sided at the ends); outside the log the end
    values are held. Differentiable in `t` (for the clock offset τ).
    """
    dt = jnp.diff(log_time)
    slope = jnp.diff(joints, axis=0) / dt[:, None]
    m = jnp.concatenate(
        [
            slope[:1],
            (slope[:-1] * dt[1:, None] + slope[1:] * dt[:-1, None]) / (dt[:-1] + dt[1:])[:, None],
            slope[-1:],
        ]
    )
    tc = jnp.clip(t, log_time[0], log_time[-1])
    i = jnp.clip(jnp.searchsorted(log_time, tc, side="right") - 1, 0, log_time.shape[0] - 2)
    h = dt[i][:, None]
    u = ((tc - log_time[i]) / dt[i])[:, None]
    h00 = (1 + 2 * u) * (1 - u) ** 2
    h10 = u * (1 - u) ** 2
    h01 = u**2 * (3 - 2 * u)
    h11 = u**2 * (u - 1)
    return h00 * joints[i] + h10 * h * m[i] + h01 * joints[i + 1] + h11 * h * m[i + 1]


def motion_direction(
    log_time: np.ndarray, joints: np.ndarray, t: np.ndarray, threshold: float = 1e-3
) -> np.ndarray:
    """Sign (±1) of each joint's motion at times `t`, holding the last direction at rest.

    `threshold` [rad/s]: slower is "at rest". Before the first motion the direction of
    the first motion is used. numpy (the direction is data, not a parameter).
    """
    v = np.gradient(joints, log_time, axis=0)
    sign = np.where(np.abs(v) > threshold, np.sign(v), 0.0)
    out = np.empty_like(sign)
    for j in range(sign.shape[1]):
        s = sign[:, j]
        idx = np.where(s != 0, np.arange(s.size), -1)
        idx = np.maximum.accumulate(idx)
        first = np.flatnonzero(s)
        held = np.where(idx >= 0, s[np.maximum(idx, 0)], s[first[0]] if first.size else 1.0)
        out[:, j] = held
    k = np.clip(np.searchsorted(log_time, t, side="right") - 1, 0, len(log_time) - 1)
    return out[k]


#: speed [rad/s] below which a joint counts as at rest for `motion_sign` (a calibration
#: may carry another, `CalibrationResult.motion_threshold`)
MOTION_THRESHOLD = 1e-3


def motion_sign(
    log_time: np.ndarray, joints: np.ndarray, t: np.ndarray, threshold: float = MOTION_THRESHOLD
) -> np.ndarray:
    """Sign (−1, 0, +1) of each joint's velocity at times `t`: 0 where the joint is slower
    than `threshold` [rad/s] (the dictionary's velocity-sign terms act only in motion;
    the threshold is data, not a parameter: changing it recompiles nothing).
    numpy (data, not a parameter)."""
    v = np.gradient(joints, log_time, axis=0)
    sign = np.where(np.abs(v) > threshold, np.sign(v), 0.0)
    k = np.clip(np.searchsorted(log_time, t, side="right") - 1, 0, len(log_time) - 1)
    return sign[k]


def effective_joints(
    robot: RobotModel,
    effects: Effects,
    q: Float[Array, " joints"],
    direction: Float[Array, " joints"],
    moving: Float[Array, " joints"] | None = None,
) -> Float[Array, " joints"]:
    """Joint angles the links really take: log + offset + backlash + gravity deflection
    + the dictionary's joint terms (`moving`: `motion_sign`, zero if None)."""
    torque = gravity_torque(robot, q)
    out = (
        q + effects.joint_offset + effects.backlash * direction + effects.joint_compliance * torque
    )
    if effects.terms:
        s = jnp.zeros_like(q) if moving is None else moving
        out = out + joint_term_error(effects.terms, q, s, torque)
    return out


def dh_corrections(
    robot: RobotModel, effects: Effects
) -> tuple[Float[Array, "joints 4"], Float[Array, " joints"]]:
    """The geometric effects as a DH-table correction ``[Δd, Δa, Δα, 0]`` and Hayati's
    tilt Δβ per link (the arguments of `forward_kinematics`)."""
    dh_delta = (
        jnp.zeros_like(robot.dh)
        .at[:, :2]
        .set(effects.link_length)
        .at[:, 2]
        .set(effects.link_twist[:, 0])
    )
    return dh_delta, effects.link_twist[:, 1]


def flange_poses(
    robot: RobotModel,
    effects: Effects,
    q: Float[Array, "n joints"],
    direction: Float[Array, "n joints"],
    moving: Float[Array, "n joints"] | None = None,
) -> jaxlie.SE3:
    """base←flange for each frame (batched SE3) with the kinematic effects applied."""
    dh_delta, tilt = dh_corrections(robot, effects)
    moving = jnp.zeros_like(q) if moving is None else moving

    def one(qq, dd, mm):
        return forward_kinematics(
            robot, effective_joints(robot, effects, qq, dd, mm), dh_delta, tilt
        )

    return jax.vmap(one)(q, direction, moving)


def camera_from_base_at(
    camera_from_base: jaxlie.SE3, effects: Effects, drift_variable: Float[Array, " n"]
) -> jaxlie.SE3:
    """camera←base per frame, translated by `thermal_drift` · drift variable (K or min)."""
    shift = drift_variable[:, None] * effects.thermal_drift[None, :]
    rot = jaxlie.SO3(jnp.broadcast_to(camera_from_base.rotation().wxyz, shift.shape[:-1] + (4,)))
    return jaxlie.SE3.from_rotation_and_translation(
        rot, camera_from_base.translation()[None] + shift
    )


def led_positions(
    camera_from_tool: jaxlie.SE3,
    effects: Effects,
    constellation: Float[Array, "leds 3"],
    normals: Float[Array, "leds 3"],
) -> Float[Array, "n leds 3"]:
    """Measured LED positions [m] in the camera frame for batched camera←tool poses.

    Applies `led_angle_bias` along each LED's emission axis (by its emission angle seen
    from the camera at the origin), the dictionary's LED terms and `tracker_scale`.
    """
    pts = jax.vmap(lambda T: jax.vmap(T.apply)(constellation))(camera_from_tool)
    nrm = jax.vmap(lambda T: jax.vmap(T.rotation().apply)(normals))(camera_from_tool)
    theta = emission_angle(pts, nrm)
    weight = (1.0 - jnp.cos(theta)) / (1.0 - np.cos(BIAS_REFERENCE_ANGLE))
    offset = (effects.led_angle_bias * weight)[..., None] * nrm
    if effects.terms:
        offset = offset + led_term_offset(effects.terms, pts, nrm, theta)
    return (1.0 + effects.tracker_scale) * (pts + offset)


def predict_tool_poses(
    robot: RobotModel,
    effects: Effects,
    camera_from_base: jaxlie.SE3,
    flange_from_tool: jaxlie.SE3,
    q: Float[Array, "n joints"],
    direction: Float[Array, "n joints"],
    drift_variable: Float[Array, " n"],
    moving: Float[Array, "n joints"] | None = None,
) -> jaxlie.SE3:
    """camera←tool for each frame from joint angles (already at t + τ) and the effects."""
    base_from_flange = flange_poses(robot, effects, q, direction, moving)
    cam = camera_from_base_at(camera_from_base, effects, drift_variable)
    return cam @ base_from_flange @ flange_from_tool
