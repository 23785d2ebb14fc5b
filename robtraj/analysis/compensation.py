"""A robot program corrected with the calibrated model (`robtraj compensate`).

For each target (TCP pose in the base frame) the joint angles at which the calibrated
model — every effect of the calibration: geometry, compliance under the gravity torque,
backlash by the direction of approach, dictionary terms and joint angle error maps —
puts the calibrated tool on the target; then the Cartesian command the controller must
be sent so that its nominal model (nominal kinematics, nominal TCP) arrives at those
joints. The nominal solution starts each calibrated one, and the target before starts
the next nominal one, so the robot stays on one branch. Both solutions must lie within
the robot's joint limits (where the model has them) as they come, not wrapped by 2π:
the robot moves continuously along its branch and cannot skip a turn.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from ..model import RobotModel, flange_poses, forward_kinematics, inverse_kinematics, pose_se3
from ..recording import Pose, Program

#: [m], [rad]: the calibrated model's TCP must reach each target this closely
TOLERANCE = (1e-6, 1e-6)
#: Gauss–Newton steps of each inverse kinematics
ITERATIONS = 60
#: [rad] a joint this far past a limit is still within it (the solver's rounding)
LIMIT_TOLERANCE = 1e-9


@dataclasses.dataclass(frozen=True)
class Compensation:
    """Per target: `commands` (`Pose` `(P, ·)`, base frame) to send the controller;
    `joints` `(P, J)` [rad] the robot then takes (the calibrated model's solution);
    `nominal_joints` the nominal model's solution for the target itself;
    `error_before_m` / `error_after_m` `(P,)` the calibrated model's TCP position error
    at the nominal and at the compensated joints (the predicted error without and with
    compensation), `error_after_rad` its orientation error."""

    commands: Pose
    joints: np.ndarray
    nominal_joints: np.ndarray
    error_before_m: np.ndarray
    error_after_m: np.ndarray
    error_after_rad: np.ndarray
    #: targets left out as out of reach (`compensate(skip_unreachable=True)`; NaN rows)
    unreachable: tuple[int, ...] = ()


def compensate(
    program: Program,
    robot: RobotModel,
    calib,
    nominal_flange_from_tool: Pose,
    q_start: np.ndarray,
    *,
    tcp: str = "nominal",
    names: list[str] | None = None,
    nominal_joints: np.ndarray | None = None,
    skip_unreachable: bool = False,
) -> Compensation:
    """Correct `program`'s targets with calibration `calib` of `robot` (see the module
    docstring). `nominal_flange_from_tool` is the controller's TCP; `q_start` `(J,)`
    [rad] seeds the first target's nominal solution. `tcp`: which tool frame the
    calibrated robot puts on each target: ``"nominal"``, the controller's TCP carried by
    the calibrated flange (what ISO 9283 and path deviation judge: the robot's own
    error), or ``"calibrated"``, the calibrated tool frame (the tool mount's error
    corrected too). `UserError` naming the targets the calibrated model cannot reach
    within `TOLERANCE` (out of reach), else the first target whose nominal or
    compensated joints leave `robot.joint_limits`, and the joint. `nominal_joints`
    `(P, J)` [rad]: the controller's own solution of each target where it is known (a
    joint log at the targets); by default each target's is solved from the one before,
    the first from `q_start`. `skip_unreachable`: leave targets out of reach out (NaN,
    listed in `Compensation.unreachable`) instead of refusing the program."""
    if tcp not in ("nominal", "calibrated"):
        raise UserError(f"tcp must be 'nominal' or 'calibrated', not {tcp!r}")
    targets = pose_se3(program.targets)
    if nominal_joints is None:
        nominal_tool = pose_se3(nominal_flange_from_tool)
        nominal = _nominal_solutions(robot, targets, nominal_tool, q_start)
    else:
        nominal = np.asarray(nominal_joints, float)
    direction = _approach_direction(nominal)
    effects = calib.effects_module(robot.n_joints)
    tool = pose_se3(calib.flange_from_tool if tcp == "calibrated" else nominal_flange_from_tool)
    joints, before, after = _calibrated_solutions(
        robot, effects, tool, targets, jnp.asarray(nominal), jnp.asarray(direction)
    )
    after = np.array(after)
    bad = np.flatnonzero(
        ~np.isfinite(after).all(1) | (np.linalg.norm(after[:, :3], axis=1) > TOLERANCE[0])
        | (np.linalg.norm(after[:, 3:], axis=1) > TOLERANCE[1])
    )  # fmt: skip
    if bad.size and skip_unreachable:
        joints = np.asarray(joints).copy()
        joints[bad] = nominal[bad]  # held for the limit check, NaN in the result
    elif bad.size:
        label = [_label(names, int(i)) for i in bad[:5]]
        p = np.round(np.asarray(program.targets.position)[bad[0]], 3).tolist()
        raise UserError(
            f"the calibrated robot cannot reach {', '.join(label)}"
            f"{' …' if bad.size > 5 else ''} (first at {p} m) within "
            f"{TOLERANCE[0] * 1e6:g} µm: out of reach"
        )
    _check_joint_limits(robot, {"nominal": nominal, "compensated": np.asarray(joints)}, names)
    commands = jax.vmap(
        lambda q: (forward_kinematics(robot, q) @ pose_se3(nominal_flange_from_tool)).wxyz_xyz
    )(joints)
    commands, joints = np.asarray(commands).copy(), np.asarray(joints).copy()
    commands[bad], joints[bad], after[bad] = np.nan, np.nan, np.nan
    return Compensation(
        commands=Pose(commands[:, 4:], commands[:, :4]),
        joints=joints,
        nominal_joints=np.asarray(nominal),
        error_before_m=np.linalg.norm(np.asarray(before)[:, :3], axis=1),
        error_after_m=np.linalg.norm(after[:, :3], axis=1),
        error_after_rad=np.linalg.norm(after[:, 3:], axis=1),
        unreachable=tuple(int(i) for i in bad),
    )


def _label(names: list[str] | None, i: int) -> str:
    return names[i] if names and names[i] else f"target {i + 1}"


def _check_joint_limits(robot: RobotModel, solutions: dict, names: list[str] | None) -> None:
    """`UserError` naming the first target, its joint and which of `solutions` (name →
    joints `(P, J)` [rad]) puts it outside `robot.joint_limits`."""
    if robot.joint_limits is None:
        return
    limits = np.asarray(robot.joint_limits, np.float64)
    outside = {
        kind: (q < limits[:, 0] - LIMIT_TOLERANCE) | (q > limits[:, 1] + LIMIT_TOLERANCE)
        for kind, q in solutions.items()
    }
    bad = np.flatnonzero(np.any([o.any(1) for o in outside.values()], axis=0))
    if not bad.size:
        return
    i = int(bad[0])
    kind = next(k for k, o in outside.items() if o[i].any())
    j = int(np.flatnonzero(outside[kind][i])[0])
    angle, (lo, hi) = np.degrees(solutions[kind][i, j]), np.degrees(limits[j])
    more = f" (and {bad.size - 1} more targets)" if bad.size > 1 else ""
    raise UserError(
        f"the {kind} joints of {_label(names, i)} put joint {j + 1} at {angle:.2f}°, "
        f"outside its limits [{lo:.2f}°, {hi:.2f}°]{more}: out of the joint limits"
    )


def _nominal_solutions(robot, targets: jaxlie.SE3, nominal_tool: jaxlie.SE3, q_start):
    """The controller's own joint solution of each target, each from the one before."""
    flanges = jaxlie.SE3(targets.wxyz_xyz) @ nominal_tool.inverse()

    def step(q_prev, pose):
        q = inverse_kinematics(robot, jaxlie.SE3(pose), q_prev, iterations=ITERATIONS)
        return q, q

    _, q = jax.lax.scan(step, jnp.asarray(q_start, jnp.float64), flanges.wxyz_xyz)
    return np.asarray(q)


def _approach_direction(joints: np.ndarray) -> np.ndarray:
    """Sign (±1) of each joint's last motion on the way to each target (backlash), held
    where a joint does not move; +1 before its first motion."""
    step = np.sign(np.diff(joints, axis=0, prepend=joints[:1]))
    step[np.abs(np.diff(joints, axis=0, prepend=joints[:1])) < 1e-9] = 0.0
    out = np.ones_like(step)
    for j in range(step.shape[1]):
        moved = np.flatnonzero(step[:, j])
        last = np.maximum.accumulate(np.where(step[:, j] != 0, np.arange(len(step)), -1))
        out[:, j] = np.where(
            last >= 0, step[np.maximum(last, 0), j], step[moved[0], j] if moved.size else 1.0
        )
    return out


@jax.jit
def _calibrated_solutions(robot, effects, tool, targets, nominal, direction):
    """Per target: the calibrated model's joint solution from the nominal one, and its
    TCP error (position [m], rotation vector [rad]) at the nominal and at that solution."""

    def pose(q, d):
        base_from_flange = flange_poses(robot, effects, q[None], d[None])
        return jaxlie.SE3(base_from_flange.wxyz_xyz[0]) @ tool

    def one(target_wxyz_xyz, q0, d):
        target = jaxlie.SE3(target_wxyz_xyz)
        q = inverse_kinematics(
            robot, target, q0, iterations=ITERATIONS, forward=lambda qq: pose(qq, d)
        )

        def err(qq):  # position [m] and rotation-vector [rad] error against the target
            at = pose(qq, d)
            turn = (target.rotation().inverse() @ at.rotation()).log()
            return jnp.concatenate([at.translation() - target.translation(), turn])

        return q, err(q0), err(q)

    return jax.vmap(one)(targets.wxyz_xyz, nominal, direction)
