"""Single-angle orientation difference (paper eq. 1-2)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._quaternion import quat_conjugate, quat_multiply


@jax.jit
def rotation_angle(
    q_a: Float[Array, "*batch 4"], q_b: Float[Array, "*batch 4"]
) -> Float[Array, "*batch"]:
    """Angle [rad] in ``[0, π]`` of the relative rotation ``q_a⁻¹ ⊗ q_b`` (wxyz).

    Independent of the orientation representation and of the quaternion signs. Computed as
    ``2·atan2(|v|, |w|)`` of the relative quaternion (w, v): ``acos`` of the trace or of
    ``w`` loses half the digits near 0 (at 1e-9 rad it returns 0 or 2e-8). Inputs need not
    be exactly normalised (the atan2 form is scale-invariant). Gradients are finite at 0.
    """
    rel = quat_multiply(quat_conjugate(q_a), q_b)
    vv = jnp.sum(rel[..., 1:] ** 2, axis=-1)
    # double-where: |v| has an infinite derivative at v = 0.
    vnorm = jnp.where(vv > 0, jnp.sqrt(jnp.where(vv > 0, vv, 1.0)), 0.0)
    return 2.0 * jnp.arctan2(vnorm, jnp.abs(rel[..., 0]))
