"""Forward kinematics against a direct numpy product of DH matrices; gradients vs FD."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from robtraj.model import (
    Effects,
    abb_irb2400_16,
    dh_corrections,
    flange_jacobian,
    forward_kinematics,
    gravity_torque,
    inverse_kinematics,
    joint_frames,
    redundant_link_parameters,
    ur10,
)


def numpy_fk(dh, q, flange_rz, tilt=None):
    """Independent reference: T = Π Rz(θ)·Tz(d)·Tx(a)·Rx(α)·Ry(β), then Rz(flange_rz)."""

    def rz(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])

    def rx(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])

    def ry(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])

    def tr(x, y, z):
        m = np.eye(4)
        m[:3, 3] = x, y, z
        return m

    t = np.eye(4)
    tilt = np.zeros(len(q)) if tilt is None else tilt
    for (d, a, alpha, off), qi, beta in zip(dh, q, tilt):
        t = t @ rz(qi + off) @ tr(0, 0, d) @ tr(a, 0, 0) @ rx(alpha) @ ry(beta)
    return t @ rz(flange_rz)


@pytest.mark.parametrize("make, flange_rz", [(abb_irb2400_16, np.pi), (ur10, 0.0)])
def test_fk_matches_numpy_dh_product(make, flange_rz):
    robot = make()
    rng = np.random.default_rng(0)
    fk = jax.jit(lambda q: forward_kinematics(robot, q).as_matrix())
    for q in rng.uniform(-np.pi, np.pi, size=(50, 6)):
        want = numpy_fk(np.asarray(robot.dh), q, flange_rz)
        np.testing.assert_allclose(np.asarray(fk(jnp.asarray(q))), want, rtol=0, atol=1e-12)


def test_geometric_effects_match_numpy_dh_product():
    """link_length, link_twist (Δα and Hayati's Δβ) against the numpy product of the
    corrected DH matrices, each followed by Ry(Δβ)."""
    robot = ur10()
    rng = np.random.default_rng(1)
    eff = Effects.zeros(6).with_value("link_length", rng.normal(0, 1e-3, (6, 2)))
    eff = eff.with_value("link_twist", rng.normal(0, 1e-2, (6, 2)))
    dh_delta, tilt = dh_corrections(robot, eff)
    dh = np.asarray(robot.dh).copy()
    dh[:, :2] += np.asarray(eff.link_length)
    dh[:, 2] += np.asarray(eff.link_twist)[:, 0]
    fk = jax.jit(lambda q: forward_kinematics(robot, q, dh_delta, tilt).as_matrix())
    for q in rng.uniform(-np.pi, np.pi, size=(20, 6)):
        want = numpy_fk(dh, q, 0.0, np.asarray(eff.link_twist)[:, 1])
        np.testing.assert_allclose(np.asarray(fk(jnp.asarray(q))), want, rtol=0, atol=1e-12)


def test_every_joint_frame_matches_numpy_dh_product_in_a_batch():
    """`joint_frames` under `vmap` (as the estimation runs it, with tilts): frame i is the
    numpy product of the first i corrected DH matrices."""
    robot = abb_irb2400_16()
    rng = np.random.default_rng(2)
    dh = np.asarray(robot.dh) + rng.normal(0, 1e-3, (6, 4))
    tilt = rng.normal(0, 1e-2, 6)
    q = rng.uniform(-np.pi, np.pi, size=(64, 6))
    kernel = jax.jit(jax.vmap(lambda a: joint_frames(jnp.asarray(dh), a, jnp.asarray(tilt))))
    got = np.asarray(kernel(jnp.asarray(q)))
    assert got.shape == (64, 7, 4, 4)
    for frames, qq in zip(got, q):
        for i in range(7):
            want = numpy_fk(dh[:i], qq[:i], 0.0, tilt[:i])
            np.testing.assert_allclose(frames[i], want, rtol=0, atol=1e-12)


def test_abb_zero_pose_matches_datasheet():
    # IRB2400-16 at all-zero joints: tool0 at x = 0.100 + 0.705·0 … = (0.94, 0, 1.455) m,
    # tool z forward (+x): ROS-Industrial abb_irb2400 URDF.
    t = np.asarray(forward_kinematics(abb_irb2400_16(), jnp.zeros(6)).as_matrix())
    np.testing.assert_allclose(t[:3, 3], [0.94, 0.0, 1.455], atol=1e-12)
    np.testing.assert_allclose(t[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_fk_gradient_matches_finite_differences():
    robot = abb_irb2400_16()
    q0 = jnp.array([0.1, 0.4, -0.2, 0.3, -0.6, 0.7])
    f = lambda q: forward_kinematics(robot, q).translation()
    jac = np.asarray(jax.jacfwd(f)(q0))
    h = 1e-6
    fd = np.stack(
        [
            (np.asarray(f(q0.at[j].add(h))) - np.asarray(f(q0.at[j].add(-h)))) / (2 * h)
            for j in range(6)
        ],
        axis=1,
    )
    np.testing.assert_allclose(jac, fd, atol=1e-8)


def test_gravity_torque_is_minus_potential_gradient_by_fd():
    # static balance: a tiny joint move δq changes potential energy by −τ·δq
    robot = abb_irb2400_16()
    q0 = jnp.array([0.0, 0.5, 0.2, 0.0, -0.4, 0.0])
    tau = np.asarray(gravity_torque(robot, q0))
    assert tau[0] == pytest.approx(0.0, abs=1e-9)  # joint 1 axis is vertical
    assert abs(tau[1]) > 100.0  # shoulder carries the arm
    from robtraj.model import joint_frames

    def potential(q):
        o = np.asarray(joint_frames(robot.dh, jnp.asarray(q)))[:, :3, 3]
        com = 0.5 * (o[:-1] + o[1:])
        fz = float(forward_kinematics(robot, jnp.asarray(q)).translation()[2])
        return 9.81 * (
            np.sum(np.asarray(robot.link_mass) * com[:, 2]) + float(robot.payload_mass) * fz
        )

    h = 1e-6
    q = np.asarray(q0)
    for j in range(6):
        dv = (potential(q + h * np.eye(6)[j]) - potential(q - h * np.eye(6)[j])) / (2 * h)
        assert tau[j] == pytest.approx(-dv, abs=1e-5)


def test_inverse_kinematics_round_trip():
    robot = abb_irb2400_16()
    q_true = jnp.array([0.2, 0.35, 0.1, 0.4, -0.7, 0.5])
    target = forward_kinematics(robot, q_true)
    q = inverse_kinematics(robot, target, q_true + 0.05)
    np.testing.assert_allclose(np.asarray(q), np.asarray(q_true), atol=1e-10)


def test_flange_jacobian_matches_autodiff():
    """The closed-form twists of `flange_jacobian` against forward-mode autodiff of the
    forward kinematics (left-perturbation twist of base←flange), at corrected DH."""
    robot = ur10()
    rng = np.random.default_rng(2)
    eff = Effects.zeros(6).with_value("link_length", rng.normal(0, 1e-3, (6, 2)))
    eff = eff.with_value("link_twist", rng.normal(0, 1e-2, (6, 2)))
    dh_delta, tilt = dh_corrections(robot, eff)

    def twist_of(p, q):
        # p = [θ, d, a, α, β] corrections (joints, 5) around the current model
        dd = dh_delta.at[:, 0].add(p[:, 1]).at[:, 1].add(p[:, 2]).at[:, 2].add(p[:, 3])
        t = forward_kinematics(robot, q + p[:, 0], dd, tilt + p[:, 4])
        t0 = forward_kinematics(robot, q, dh_delta, tilt)
        return (t @ t0.inverse()).log()

    for q in rng.uniform(-np.pi, np.pi, size=(5, 6)):
        q = jnp.asarray(q)
        want = jax.jacfwd(twist_of)(jnp.zeros((6, 5)), q)  # (6, joints, 5)
        pose, got = flange_jacobian(robot, q, dh_delta, tilt)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            pose.as_matrix(),
            forward_kinematics(robot, q, dh_delta, tilt).as_matrix(),
            rtol=0,
            atol=1e-15,
        )


def test_redundant_link_parameters_follow_the_axes():
    """Hayati's tilt only where consecutive axes are parallel; never the last link's axis."""
    last = ("link_twist[5].alpha", "link_twist[5].beta")
    assert redundant_link_parameters(ur10()) == (
        "link_twist[0].beta",
        "link_twist[3].beta",
        "link_twist[4].beta",
        *last,
    )
    assert redundant_link_parameters(abb_irb2400_16()) == (
        "link_twist[0].beta",
        "link_twist[2].beta",
        "link_twist[3].beta",
        "link_twist[4].beta",
        *last,
    )
