"""The right Jacobian of SE3's exponential map (jaxlie has the group, not this)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

#: terms of the series: the first left out is below 1e-13 of the identity for rotations
#: up to π (|θ|^27/27!)
_TERMS = 26


def _hat(v: Float[Array, "3"]) -> Float[Array, "3 3"]:
    x, y, z = v[0], v[1], v[2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y]), jnp.stack([z, o, -x]), jnp.stack([-y, x, o])])


def se3_right_jacobian(tangent: Float[Array, "6"]) -> Float[Array, "6 6"]:
    """``Jr(ξ)`` with ``exp(ξ + δ) = exp(ξ)·exp(Jr(ξ)·δ + O(δ²))`` for a jaxlie SE3 tangent
    ``ξ = [tx, ty, tz, rx, ry, rz]``: ``Σ_k (−ad ξ)^k / (k+1)!`` summed by Horner's rule
    (exact to rounding for rotations up to π, no small-angle branch; a few 6×6
    products, so it adds little to a compiled kernel, unlike differentiating
    ``exp``/``log``)."""
    rho, phi = tangent[:3], tangent[3:]
    w, r = _hat(phi), _hat(rho)
    ad = jnp.concatenate(
        [jnp.concatenate([w, r], 1), jnp.concatenate([jnp.zeros_like(w), w], 1)], 0
    )
    eye = jnp.eye(6, dtype=tangent.dtype)
    out = eye
    for k in range(_TERMS, 0, -1):
        out = eye - (ad @ out) / (k + 1)
    return out
