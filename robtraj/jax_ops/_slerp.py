"""Spherical linear interpolation of unit quaternions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


@jax.jit
def slerp(
    q0: Float[Array, "*batch 4"], q1: Float[Array, "*batch 4"], s: Float[Array, "..."] | float
) -> Float[Array, "*batch 4"]:
    """Slerp from `q0` (``s = 0``) to `q1` (``s = 1``), wxyz, along the shorter arc.

    Constant angular velocity about a fixed axis (paper section 4). The half-angle is
    ``θ = 2·atan2(|q1 - q0|, |q1 + q0|)`` (stable near 0) and the weights are written with
    ``sinc`` so nearly equal quaternions interpolate without 0/0, with finite gradients.
    `s` broadcasts against the leading dims; the result is normalised.
    """
    s = jnp.asarray(s, dtype=q0.dtype)
    dot = jnp.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = jnp.where(dot < 0, -q1, q1)  # shortest path
    theta = 2.0 * jnp.arctan2(
        _safe_norm(q1 - q0), _safe_norm(q1 + q0)
    )  # angle between q0 and q1 in R^4
    s = s[..., None]
    inv_pi = 1.0 / jnp.pi
    # sin(a θ) / sin θ = a · sinc(a θ / π) / sinc(θ / π), with θ <= π/2 so no 0/0.
    denom = jnp.sinc(theta * inv_pi)
    c0 = (1.0 - s) * jnp.sinc((1.0 - s) * theta * inv_pi) / denom
    c1 = s * jnp.sinc(s * theta * inv_pi) / denom
    q = c0 * q0 + c1 * q1
    return q / _safe_norm(q)


def _safe_norm(x: Array) -> Array:
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    return jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
