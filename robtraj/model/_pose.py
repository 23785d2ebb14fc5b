"""A stored `Pose` as a jaxlie transform."""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie


def pose_se3(pose) -> jaxlie.SE3:
    """`pose` (`robtraj.recording.Pose`: `position` `(..., 3)` [m], unit
    `quaternion_wxyz` `(..., 4)`, any batch shape) as a (batched) `jaxlie.SE3`."""
    return jaxlie.SE3(
        jnp.concatenate(
            [
                jnp.asarray(pose.quaternion_wxyz, jnp.float64),
                jnp.asarray(pose.position, jnp.float64),
            ],
            axis=-1,
        )
    )
