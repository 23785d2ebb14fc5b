"""`se3_right_jacobian` against independent references: the integral definition
``Jr(ξ) = ∫₀¹ exp(−s·ad ξ) ds`` through SciPy's matrix exponential of the augmented
matrix ``[[−ad ξ, I], [0, 0]]``, and its defining property through jaxlie's exp/log."""

import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from scipy.linalg import expm

from robtraj.jax_ops import se3_right_jacobian


def _ad(xi: np.ndarray) -> np.ndarray:
    def hat(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = hat(xi[3:])
    out[:3, 3:] = hat(xi[:3])
    return out


def _reference(xi: np.ndarray) -> np.ndarray:
    aug = np.zeros((12, 12))
    aug[:6, :6] = -_ad(xi)
    aug[:6, 6:] = np.eye(6)
    return expm(aug)[:6, 6:]


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-6, 1e-3, 0.3, 1.0, 2.5])
def test_right_jacobian_is_the_integral_of_the_adjoint_exponential(scale):
    """Rotations of `scale` rad (up to 2.5 rad), translations of `scale` m."""
    rng = np.random.default_rng(7)
    for _ in range(5):
        xi = rng.normal(size=6)
        xi[3:] /= np.linalg.norm(xi[3:])
        xi *= scale
        got = np.asarray(se3_right_jacobian(jnp.asarray(xi)))
        np.testing.assert_allclose(got, _reference(xi), rtol=0, atol=1e-13)


def test_right_jacobian_maps_a_tangent_step_to_the_local_one():
    """``log(exp(ξ)⁻¹ · exp(ξ + δ)) = Jr(ξ)·δ + O(|δ|²)``, through jaxlie at 1e-6 steps."""
    rng = np.random.default_rng(3)
    for _ in range(10):
        xi = rng.normal(size=6) * 0.5
        d = rng.normal(size=6) * 1e-6
        local = (
            jaxlie.SE3.exp(jnp.asarray(xi)).inverse() @ jaxlie.SE3.exp(jnp.asarray(xi + d))
        ).log()
        got = np.asarray(se3_right_jacobian(jnp.asarray(xi))) @ d
        np.testing.assert_allclose(np.asarray(local), got, rtol=0, atol=1e-11)
