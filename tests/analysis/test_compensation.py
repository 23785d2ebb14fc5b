"""`robtraj.analysis.compensation`: joint angles that put the calibrated model's TCP on each
target (forward check on 1000 targets along a walk through the workspace), commands the
nominal model turns into those joints, and targets out of reach or beyond a joint limit
refused by name."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from robtraj._errors import UserError
from robtraj.analysis.compensation import compensate
from robtraj.estimate.calibration import CalibrationResult
from robtraj.model import Effects, abb_irb2400_16, flange_poses, forward_kinematics
from robtraj.recording import Pose, Program
from robtraj.sim._simulate import Q_SEED

ROBOT = abb_irb2400_16()
NOMINAL_TCP = Pose(np.array([0.0, 0.0, 0.12]), np.array([1.0, 0.0, 0.0, 0.0]))


def _se3(p: Pose) -> jaxlie.SE3:
    return jaxlie.SE3(
        jnp.concatenate([jnp.asarray(p.quaternion_wxyz), jnp.asarray(p.position)], -1)
    )


def _calibration(rng) -> CalibrationResult:
    effects = {
        "joint_offset": rng.normal(scale=5e-4, size=6),
        "link_length": rng.normal(scale=3e-4, size=(6, 2)),
        "link_twist": rng.normal(scale=2e-4, size=(6, 2)),
        "joint_compliance": np.full(6, 1.5e-6),
        "backlash": np.full(6, 5e-5),
    }
    return CalibrationResult.from_json({
        "camera_from_base": {"position": [3, 0, 1], "quaternion_wxyz": [1, 0, 0, 0]},
        "flange_from_tool": {"position": [0.0005, -0.0003, 0.1204], "quaternion_wxyz": [1, 0, 0, 0]},
        "constellation": {"led_ids": [1, 2, 3], "positions": np.eye(3).tolist()},
        "effects": {k: v.tolist() for k, v in effects.items()},
    })  # fmt: skip


def _walk(rng, n=1000):
    """Targets (nominal TCP poses) along a walk through joint space: each joint swings
    about the seed (amplitudes up to 1 rad) at its own, randomly varying pace, so no
    joint ever stands still between two targets."""
    pace = np.cumsum(rng.uniform(0.01, 0.06, size=(n, 6)), axis=0)
    amplitude = np.array([1.0, 0.5, 0.5, 1.0, 0.6, 1.0])
    q = np.asarray(Q_SEED) + amplitude * np.sin(pace + rng.uniform(0, 2 * np.pi, 6))
    q[:, 4] -= 0.6  # the wrist away from its singularity at q5 = 0
    poses = jax.vmap(lambda qq: (forward_kinematics(ROBOT, qq) @ _se3(NOMINAL_TCP)).wxyz_xyz)(
        jnp.asarray(q)
    )
    poses = np.asarray(poses)
    return Program(Pose(poses[:, 4:], poses[:, :4]), np.array(["joint"] * n), np.zeros(n)), q


@pytest.mark.parametrize("tcp", ["nominal", "calibrated"])
def test_compensated_joints_put_the_calibrated_tcp_on_1000_targets(tcp):
    rng = np.random.default_rng(5)
    calib = _calibration(rng)
    program, q_walk = _walk(rng)
    res = compensate(program, ROBOT, calib, NOMINAL_TCP, q_walk[0], tcp=tcp)
    # forward check, independently of the solver's own error: the calibrated model
    # (every effect, backlash by the approach direction) at the compensated joints
    eff = Effects.from_dict(calib.effects, 6)
    # backlash acts by the direction of approach: the sign of each joint's last step
    # (the first target: that of the step after it)
    step = np.sign(np.diff(res.nominal_joints, axis=0))
    assert np.all(step != 0)
    direction = np.concatenate([step[:1], step])
    tool = _se3(calib.flange_from_tool if tcp == "calibrated" else NOMINAL_TCP)
    flange = flange_poses(ROBOT, eff, jnp.asarray(res.joints), jnp.asarray(direction))
    at = np.asarray(jax.vmap(lambda f: (jaxlie.SE3(f) @ tool).translation())(flange.wxyz_xyz))
    err = np.linalg.norm(at - program.targets.position, axis=1)
    assert err.max() < 1e-6
    assert res.error_before_m.min() > 1e-5  # the effects move the TCP: there was work to do
    # the controller's nominal model turns each command into the compensated joints
    cmd_flange = jax.vmap(lambda c: (c @ _se3(NOMINAL_TCP).inverse()).wxyz_xyz)(_se3(res.commands))
    back = jax.vmap(lambda f, q0: forward_kinematics(ROBOT, q0).wxyz_xyz)(
        cmd_flange, jnp.asarray(res.joints)
    )
    np.testing.assert_allclose(np.asarray(back), np.asarray(cmd_flange), atol=1e-9)


def test_targets_out_of_reach_are_refused_by_name():
    rng = np.random.default_rng(1)
    program, q_walk = _walk(rng, n=5)
    far = program.targets.position.copy()
    far[3] = [4.0, 0.0, 1.0]
    program = Program(Pose(far, program.targets.quaternion_wxyz), program.motion, program.speed)
    with pytest.raises(UserError, match="cannot reach P4"):
        compensate(
            program,
            ROBOT,
            _calibration(rng),
            NOMINAL_TCP,
            q_walk[0],
            names=[f"P{i + 1}" for i in range(5)],
        )


def test_targets_out_of_reach_can_be_left_out_and_the_rest_is_unchanged():
    """`skip_unreachable`: the far target is listed and NaN, the others are compensated
    as without it (given the controller's own joints, each target on its own)."""
    rng = np.random.default_rng(1)
    program, q_walk = _walk(rng, n=5)
    calib = _calibration(rng)
    far = program.targets.position.copy()
    far[3] = [4.0, 0.0, 1.0]
    bad = Program(Pose(far, program.targets.quaternion_wxyz), program.motion, program.speed)
    got = compensate(
        bad, ROBOT, calib, NOMINAL_TCP, q_walk[0], nominal_joints=q_walk, skip_unreachable=True
    )
    ref = compensate(program, ROBOT, calib, NOMINAL_TCP, q_walk[0], nominal_joints=q_walk)
    assert got.unreachable == (3,) and np.all(np.isnan(got.joints[3]))
    keep = [0, 1, 2, 4]
    np.testing.assert_allclose(got.joints[keep], ref.joints[keep], rtol=0, atol=1e-12)
    assert np.all(got.error_after_m[keep] < 1e-6)


def _with_limit(joint: int, upper: float):
    """`ROBOT` with joint `joint`'s upper limit at `upper` [rad]."""
    limits = np.asarray(ROBOT.joint_limits).copy()
    limits[joint, 1] = upper
    return eqx.tree_at(lambda r: r.joint_limits, ROBOT, jnp.asarray(limits))


@pytest.mark.parametrize("solution", ["nominal", "compensated"])
def test_a_target_beyond_a_joint_limit_is_refused_by_name(solution):
    """A joint's upper limit just below the largest angle of it that one target needs:
    in its nominal solution, or in its compensated joints where they go beyond every
    nominal solution's."""
    rng = np.random.default_rng(1)
    program, q_walk = _walk(rng, n=8)
    calib, names = _calibration(rng), [f"P{i + 1}" for i in range(8)]
    free = compensate(program, ROBOT, calib, NOMINAL_TCP, q_walk[0], names=names)
    np.testing.assert_allclose(free.nominal_joints, q_walk, atol=1e-9)
    chosen, other = (free.nominal_joints, free.joints)[:: 1 if solution == "nominal" else -1]
    # a joint that goes furthest in the chosen solution, the limit below that angle alone
    joint = int(np.argmax(chosen.max(0) - other.max(0)))
    worst = int(np.argmax(chosen[:, joint]))
    second = np.sort(np.concatenate([chosen[:, joint], other[:, joint]]))[-2]
    assert chosen[worst, joint] > other[:, joint].max()
    limit = 0.5 * (chosen[worst, joint] + second)
    with pytest.raises(UserError) as e:
        compensate(program, _with_limit(joint, limit), calib, NOMINAL_TCP, q_walk[0], names=names)
    message = str(e.value)
    assert f"the {solution} joints of P{worst + 1} put joint {joint + 1} at" in message, message
    assert f"{np.degrees(limit):.2f}°]" in message and "\n" not in message
