"""Standard-DH forward kinematics, built-in robots and numerical inverse kinematics.

Frames: `base` (robot base, z up), `flange` (tool0). A DH row is
``[d, a, alpha, theta_offset]`` [m, m, rad, rad] and the link transform is
``Rz(q + theta_offset) · Tz(d) · Tx(a) · Rx(alpha)`` (standard/distal DH).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from .._errors import UserError
from ..recording import RobotLog

_PI = np.pi


class RobotModel(eqx.Module):
    """A serial robot: DH table, flange offset and a link-mass model for gravity torques.

    - `dh`: `(joints, 4)` rows ``[d, a, alpha, theta_offset]`` [m, m, rad, rad].
    - `last_from_flange`: `(7,)` jaxlie ``wxyz_xyz`` of the flange (tool0) in the last
      DH frame.
    - `link_mass`: `(joints,)` [kg], mass of link i, lumped at the midpoint between the
      origins of DH frames i-1 and i; `payload_mass` [kg] lumped at the flange.
    - `joint_limits`: `(joints, 2)` [rad] each joint's range ``[lower, upper]`` in the
      DH joint angle q (−inf / +inf where a side has no limit), or None where the
      limits are not known (every joint unlimited).
    """

    dh: Float[Array, "joints 4"]
    last_from_flange: Float[Array, "7"]
    link_mass: Float[Array, " joints"]
    payload_mass: Float[Array, ""]
    name: str = eqx.field(static=True, default="custom")
    joint_limits: Float[Array, "joints 2"] | None = None

    @property
    def n_joints(self) -> int:
        return self.dh.shape[0]


def _robot(name, dh, flange_rz, masses, payload, limits_deg=None) -> RobotModel:
    last_from_flange = jaxlie.SE3.from_rotation(jaxlie.SO3.from_z_radians(flange_rz))
    limits = None if limits_deg is None else jnp.asarray(np.deg2rad(limits_deg), jnp.float64)
    return RobotModel(
        dh=jnp.asarray(dh, jnp.float64),
        last_from_flange=last_from_flange.wxyz_xyz.astype(jnp.float64),
        link_mass=jnp.asarray(masses, jnp.float64),
        payload_mass=jnp.asarray(payload, jnp.float64),
        name=name,
        joint_limits=limits,
    )


def abb_irb2400_16() -> RobotModel:
    """ABB IRB2400-16 (ROS-Industrial DH; tool0 = last DH frame turned by π about z).

    Joint limits: the data sheet's axis ranges (±180°, −100…110°, −60…65°, ±200°,
    ±120°, ±400°), in the DH joint angles (ROS-Industrial's URDF carries the same)."""
    dh = [
        [0.615, 0.100, -_PI / 2, 0.0],
        [0.0, 0.705, 0.0, -_PI / 2],
        [0.0, 0.135, -_PI / 2, 0.0],
        [0.755, 0.0, _PI / 2, 0.0],
        [0.0, 0.0, -_PI / 2, 0.0],
        [0.085, 0.0, 0.0, 0.0],
    ]
    limits = [[-180, 180], [-100, 110], [-60, 65], [-200, 200], [-120, 120], [-400, 400]]
    masses = [90.0, 45.0, 35.0, 12.0, 6.0, 1.0]
    return _robot("abb_irb2400_16", dh, _PI, masses, 2.5, limits)


def ur10() -> RobotModel:
    """Universal Robots UR10 (manufacturer's published standard-DH parameters); joint
    limits ±360° on every joint (the data sheet's working range)."""
    dh = [
        [0.1273, 0.0, _PI / 2, 0.0],
        [0.0, -0.612, 0.0, 0.0],
        [0.0, -0.5723, 0.0, 0.0],
        [0.163941, 0.0, _PI / 2, 0.0],
        [0.1157, 0.0, -_PI / 2, 0.0],
        [0.0922, 0.0, 0.0, 0.0],
    ]
    return _robot("ur10", dh, 0.0, [7.1, 12.7, 4.3, 2.0, 2.0, 0.4], 1.0, [[-360, 360]] * 6)


BUILTIN_ROBOTS = {"abb_irb2400_16": abb_irb2400_16, "ur10": ur10}


def robot_from_log(log: RobotLog) -> RobotModel:
    """The robot of a recording's robot log (`/robot`).

    A `dh` table gives a custom robot: its `flange` (the flange in the last DH frame,
    identity if None), `link_mass` (5 kg per link if None), `payload_mass` (1 kg if
    None) and `joint_limits` (unlimited if None). Otherwise the named built-in `model`,
    with its flange, link masses, payload and joint limits replaced by the log's where
    given.
    """
    dh, model, flange, link_mass = log.dh, log.model, log.flange, log.link_mass
    if dh is not None:
        j = np.asarray(dh).shape[0]
        robot = _robot(model or "custom", dh, 0.0, np.full(j, 5.0), 1.0)
    elif model is None:
        raise UserError("the recording names no robot model and has no /robot/dh table")
    elif model not in BUILTIN_ROBOTS:
        raise UserError(
            f"unknown robot model {model!r} (built in: {', '.join(sorted(BUILTIN_ROBOTS))}); "
            "store a /robot/dh table instead"
        )
    else:
        robot = BUILTIN_ROBOTS[model]()
    if flange is not None:
        pose = jaxlie.SE3.from_rotation_and_translation(
            jaxlie.SO3(jnp.asarray(flange.quaternion_wxyz, jnp.float64)).normalize(),
            jnp.asarray(flange.position, jnp.float64),
        )
        robot = eqx.tree_at(lambda r: r.last_from_flange, robot, pose.wxyz_xyz)
    if link_mass is not None:
        mass = jnp.asarray(link_mass, jnp.float64)
        if mass.shape != (robot.n_joints,):
            raise UserError(
                f"/robot/link_mass has shape {mass.shape}, the robot has {robot.n_joints} joints"
            )
        robot = eqx.tree_at(lambda r: r.link_mass, robot, mass)
    if log.payload_mass is not None:
        payload = jnp.asarray(float(log.payload_mass), jnp.float64)
        robot = eqx.tree_at(lambda r: r.payload_mass, robot, payload)
    if log.joint_limits is not None:
        limits = jnp.asarray(log.joint_limits, jnp.float64)
        if limits.shape != (robot.n_joints, 2):
            raise UserError(
                f"/robot/joint_limits has shape {limits.shape}, expected ({robot.n_joints}, 2)"
            )
        robot = eqx.tree_at(lambda r: r.joint_limits, robot, limits, is_leaf=lambda x: x is None)
    return robot


def joint_frames(
    dh: Float[Array, "joints 4"],
    q: Float[Array, " joints"],
    tilt: Float[Array, " joints"] | None = None,
) -> Float[Array, "n 4 4"]:
    """Homogeneous transforms base←frame_i for i = 0 … joints (frame 0 is the base):
    frame i = frame i−1 · Rz(qᵢ + θ₀ᵢ) · Tz(dᵢ) · Tx(aᵢ) · Rx(αᵢ) · Ry(βᵢ).

    `tilt` [rad]: Hayati's turn β of each frame about its own y axis (zero if None).
    Each step turns the frame's axes as 3-vectors: under `vmap` a batch of 4×4 matrix
    products (tiny reductions) is slow on CPU."""
    dh = dh.astype(q.dtype)
    tilt = jnp.zeros_like(dh[:, 0]) if tilt is None else tilt.astype(q.dtype)
    theta, alpha = q + dh[:, 3], dh[:, 2]
    trig = [jnp.cos(theta), jnp.sin(theta), jnp.cos(alpha), jnp.sin(alpha)]
    rows = jnp.stack([dh[:, 0], dh[:, 1], *trig, jnp.cos(tilt), jnp.sin(tilt)], -1)

    def step(frame, row):
        x, y, z, o = frame
        d, a, ct, st, ca, sa, cb, sb = row
        xt, yt = x * ct + y * st, y * ct - x * st  # · Rz(θ)
        o = o + d * z + a * xt  # · Tz(d) Tx(a)
        y, za = yt * ca + z * sa, z * ca - yt * sa  # · Rx(α)
        x, z = xt * cb - za * sb, xt * sb + za * cb  # · Ry(β)
        return (x, y, z, o), jnp.stack([x, y, z, o], -1)

    eye = jnp.eye(4, dtype=q.dtype)
    first = (eye[:3, 0], eye[:3, 1], eye[:3, 2], eye[:3, 3])
    _, frames = jax.lax.scan(step, first, rows)
    bottom = jnp.broadcast_to(eye[3:], (frames.shape[0], 1, 4))
    return jnp.concatenate([eye[None], jnp.concatenate([frames, bottom], 1)], axis=0)


def forward_kinematics(
    robot: RobotModel,
    q: Float[Array, " joints"],
    dh_delta: Float[Array, "joints 4"] | None = None,
    tilt: Float[Array, " joints"] | None = None,
) -> jaxlie.SE3:
    """Flange (tool0) pose in the base frame for one joint vector `q` [rad].

    `dh_delta` is added to the DH table (link-length, twist and offset corrections);
    `tilt` [rad] turns each link frame about its y axis (Hayati's parameter).
    """
    dh = robot.dh if dh_delta is None else robot.dh + dh_delta
    base_from_last = joint_frames(dh, q, tilt)[-1]
    return jaxlie.SE3.from_matrix(base_from_last) @ jaxlie.SE3(robot.last_from_flange)


def redundant_link_parameters(robot: RobotModel) -> tuple[str, ...]:
    """`link_twist` entries that the other geometric parameters already cover, so that
    they are never estimated: Hayati's Δβ of a link whose axes are not parallel
    (|sin α| > 0.5: standard DH describes a tilt about y there through the next joint's
    offset and d) and the last link's Δα, Δβ (the tool frame's orientation)."""
    alpha = np.asarray(robot.dh)[:, 2]
    last = robot.n_joints - 1
    out = [f"link_twist[{j}].beta" for j in range(last) if abs(np.sin(alpha[j])) > 0.5]
    return (*out, f"link_twist[{last}].alpha", f"link_twist[{last}].beta")


def flange_jacobian(
    robot: RobotModel,
    q: Float[Array, " joints"],
    dh_delta: Float[Array, "joints 4"] | None = None,
    tilt: Float[Array, " joints"] | None = None,
) -> tuple[jaxlie.SE3, Float[Array, "6 joints 5"]]:
    """base←flange (as `forward_kinematics`) and its derivatives in closed form.

    Column ``[:, j, k]`` is the base-frame twist ``(v, ω)`` of the flange per unit change
    of link j's ``[θ, d, a, α, β]`` (rad, m, m, rad, rad): a change δ moves the flange to
    ``SE3.exp(δ · column) @ base_from_flange`` to first order. A joint angle turns what
    lies beyond about zⱼ through its origin; d and a translate along zⱼ and the turned
    xⱼ; α turns about that x axis and β about yⱼ₊₁, both through the next origin.
    """
    dh = robot.dh if dh_delta is None else robot.dh + dh_delta
    frames = joint_frames(dh, q, tilt)
    rot, origin = frames[:-1, :3, :3], frames[:-1, :3, 3]
    nxt_origin, nxt_y = frames[1:, :3, 3], frames[1:, :3, 1]
    z = rot[:, :, 2]
    theta = q + dh[:, 3].astype(q.dtype)
    x_turned = rot[:, :, 0] * jnp.cos(theta)[:, None] + rot[:, :, 1] * jnp.sin(theta)[:, None]
    zero = jnp.zeros_like(z)

    def turn(axis, through):
        return jnp.concatenate([jnp.cross(through, axis), axis], -1)

    def shift(axis):
        return jnp.concatenate([axis, zero], -1)

    cols = jnp.stack(
        [
            turn(z, origin),
            shift(z),
            shift(x_turned),
            turn(x_turned, nxt_origin),
            turn(nxt_y, nxt_origin),
        ],
        -1,
    )  # (joints, 6, 5)
    pose = jaxlie.SE3.from_matrix(frames[-1]) @ jaxlie.SE3(robot.last_from_flange)
    return pose, jnp.moveaxis(cols, 0, 1)


def gravity_torque(
    robot: RobotModel, q: Float[Array, " joints"], g: float = 9.81
) -> Float[Array, " joints"]:
    """Joint torques [N·m] that gravity (−z of the base) exerts, from the link-mass model.

    τ = −∂V/∂q with V the potential energy of the lumped link masses (each at the middle
    of its link, i.e. half at either joint origin) and the payload (at the flange), in
    closed form: joint i turns what lies beyond it about its axis zᵢ through oᵢ, so
    ``∂V/∂qᵢ = g·[zᵢ × (Mᵢ − Wᵢ·oᵢ)]_z`` with Wᵢ the mass and Mᵢ the mass moment beyond it.
    """
    frames = joint_frames(robot.dh, q)
    origin = frames[:, :3, 3]  # (joints + 1, 3), base first
    axis = frames[:-1, :3, 2]  # joint i turns about z of frame i
    flange = frames[-1, :3] @ jaxlie.SE3(robot.last_from_flange).as_matrix()[:, 3].astype(q.dtype)
    m = jnp.asarray(robot.link_mass, q.dtype)
    zero = jnp.zeros(1, q.dtype)
    w = 0.5 * (jnp.concatenate([zero, m]) + jnp.concatenate([m, zero]))  # per origin
    beyond_w = jnp.cumsum(w[::-1])[::-1][1:] + robot.payload_mass
    beyond_m = (
        jnp.cumsum((w[:, None] * origin)[::-1], axis=0)[::-1][1:]
        + robot.payload_mass * flange[None]
    )
    r = beyond_m - beyond_w[:, None] * origin[:-1]
    return -g * (axis[:, 0] * r[:, 1] - axis[:, 1] * r[:, 0])


def inverse_kinematics(
    robot: RobotModel,
    base_from_flange: jaxlie.SE3,
    q0: Float[Array, " joints"],
    iterations: int = 60,
    damping: float = 1e-10,
    forward=None,
) -> Float[Array, " joints"]:
    """Joint vector reaching `base_from_flange` by damped Gauss–Newton from seed `q0`.

    `forward`: the pose as a function of the joint vector (default: the nominal
    `forward_kinematics(robot, q)`; e.g. a calibrated model's base←tool, with the target
    then a tool pose)."""
    forward = (lambda q: forward_kinematics(robot, q)) if forward is None else forward

    def err(q):
        return (base_from_flange.inverse() @ forward(q)).log()

    def body(q, _):
        e = err(q)
        jac = jax.jacfwd(err)(q)
        h = jac.T @ jac + damping * jnp.eye(q.shape[0], dtype=q.dtype)
        step = jnp.linalg.solve(h, jac.T @ e)
        # limit the step so far seeds do not jump to another branch
        scale = jnp.minimum(1.0, 0.5 / (jnp.max(jnp.abs(step)) + 1e-30))
        return q - scale * step, None

    q, _ = jax.lax.scan(body, q0, None, length=iterations)
    return q
