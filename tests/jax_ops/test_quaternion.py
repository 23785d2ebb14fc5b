"""rotation_angle, slerp and the quaternion helpers against scipy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from robtraj.jax_ops import (
    matrix_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    rotation_angle,
    slerp,
)

_slerp_grad = jax.jit(jax.grad(lambda a, b: jnp.sum(slerp(a, b, 0.3)), argnums=(0, 1)))


def _wxyz(r: Rotation) -> np.ndarray:
    return r.as_quat(scalar_first=True)


def _perturbed(base: Rotation, angles: np.ndarray, seed: int) -> Rotation:
    axis = np.random.default_rng(seed).normal(size=(len(angles), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return base * Rotation.from_rotvec(axis * angles[:, None])


def test_rotation_angle_matches_scipy_including_tiny_and_near_pi():
    ra = Rotation.random(60, random_state=0)
    angles = np.concatenate(
        [np.logspace(-12, 0, 20), np.pi - np.logspace(-9, -1, 20), np.linspace(0, np.pi, 20)]
    )
    rb = _perturbed(ra, angles, 1)
    got = np.asarray(rotation_angle(jnp.asarray(_wxyz(ra)), jnp.asarray(_wxyz(rb))))
    np.testing.assert_allclose(got, (ra.inv() * rb).magnitude(), rtol=1e-9, atol=2e-15)
    # where acos fails (it returns 0 or ~2e-8 below 1e-8 rad): error stays at the
    # rounding of the inputs (~1e-16 rad absolute)
    np.testing.assert_allclose(got[:20], angles[:20], rtol=1e-12, atol=4e-16)
    assert abs(got[6] / angles[6] - 1) < 1e-6  # ~6e-9 rad
    # sign of either quaternion does not matter; batched over leading dims
    qa = jnp.asarray(_wxyz(ra)).reshape(6, 10, 4)
    qb = -jnp.asarray(_wxyz(rb)).reshape(6, 10, 4)
    np.testing.assert_allclose(np.asarray(rotation_angle(qa, qb)).ravel(), got, atol=1e-15)


def test_rotation_angle_float32_and_gradient_at_zero():
    q = jnp.asarray(_wxyz(Rotation.random(5, random_state=2)), jnp.float32)
    assert rotation_angle(q, q).dtype == jnp.float32
    g = jax.grad(lambda x: jnp.sum(rotation_angle(x, x * 1.0)))(q.astype(jnp.float64))
    assert np.all(np.isfinite(np.asarray(g)))


def test_slerp_matches_scipy():
    r = Rotation.random(2, random_state=3)
    s = np.linspace(0, 1, 11)
    want = Slerp([0, 1], r)(s)
    q0 = jnp.broadcast_to(jnp.asarray(_wxyz(r[0])), (11, 4))
    q1 = jnp.broadcast_to(jnp.asarray(_wxyz(r[1])), (11, 4))
    got = np.asarray(slerp(q0, -q1, jnp.asarray(s)))  # -q1: still the shorter path
    np.testing.assert_allclose(
        np.asarray(rotation_angle(jnp.asarray(got), jnp.asarray(_wxyz(want)))), 0, atol=1e-14
    )
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 3.0])
def test_slerp_nearly_equal_and_gradients(angle):
    r0 = Rotation.random(4, random_state=4)
    r1 = _perturbed(r0, np.full(4, angle), 5)
    q0, q1 = jnp.asarray(_wxyz(r0)), jnp.asarray(_wxyz(r1))
    s = jnp.array([0.0, 0.25, 0.5, 1.0])
    got = slerp(q0, q1, s)
    assert np.all(np.isfinite(np.asarray(got)))
    np.testing.assert_allclose(
        np.asarray(rotation_angle(q0, got)), angle * np.asarray(s), rtol=1e-8, atol=1e-15
    )
    g = _slerp_grad(q0, q1)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)


def test_quaternion_helpers_match_scipy():
    ra, rb = Rotation.random(50, random_state=6), Rotation.random(50, random_state=7)
    qa, qb = jnp.asarray(_wxyz(ra)), jnp.asarray(_wxyz(rb))
    np.testing.assert_allclose(np.asarray(quat_to_matrix(qa)), ra.as_matrix(), atol=1e-15)
    prod = np.asarray(quat_to_matrix(quat_multiply(qa, qb)))
    np.testing.assert_allclose(prod, (ra * rb).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(
        np.asarray(quat_to_matrix(quat_conjugate(qa))), ra.inv().as_matrix(), atol=1e-15
    )
    v = np.random.default_rng(8).normal(size=(50, 3))
    np.testing.assert_allclose(np.asarray(quat_rotate(qa, jnp.asarray(v))), ra.apply(v), atol=1e-14)


def test_matrix_to_quat_all_branches_and_w_nonnegative():
    angles = np.concatenate([np.zeros(1), np.full(3, np.pi), np.full(3, np.pi - 1e-7), [1.0]])
    axes = np.array([[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    axes = (
        np.vstack([axes, [[1, 2, 3]]])
        / np.linalg.norm(np.vstack([axes, [[1, 2, 3]]]), axis=1)[:, None]
    )
    r = Rotation.concatenate(
        [Rotation.from_rotvec(axes * angles[:, None]), Rotation.random(20, random_state=9)]
    )
    q = np.asarray(matrix_to_quat(jnp.asarray(r.as_matrix())))
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(
        np.asarray(quat_to_matrix(jnp.asarray(q))), r.as_matrix(), atol=1e-14
    )
    want = _wxyz(r)
    want = np.where(want[:, :1] < 0, -want, want)
    np.testing.assert_allclose(np.abs(q), np.abs(want), atol=1e-14)
