"""The residual of a 6-DOF observation: a tracker's measured pose of the probe (the tool)
against the model's prediction, in the tracker frame."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Float


def probe_pose_error(
    rotation_wxyz: Float[Array, "n 4"],
    position: Float[Array, "n 3"],
    measured: Float[Array, "n 7"],
) -> Float[Array, "n 6"]:
    """Predicted minus measured camera←probe per pose: the position error [m] in the
    camera frame (`position` as the tracker would report it, its scale applied), then
    the rotation vector [rad] of measured⁻¹·predicted (`measured` ``wxyz_xyz``)."""
    dp = position - measured[:, 4:]
    dr = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        measured[:, :4], rotation_wxyz
    )
    return jnp.concatenate([dp, dr], -1)
