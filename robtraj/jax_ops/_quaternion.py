"""Batched unit-quaternion helpers, w, x, y, z order, leading dims broadcast."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Float


@jax.jit
def quat_multiply(
    q_a: Float[Array, "*batch 4"], q_b: Float[Array, "*batch 4"]
) -> Float[Array, "*batch 4"]:
    """Hamilton product ``q_a ⊗ q_b`` (rotation q_b first, then q_a), wxyz."""
    aw, ax, ay, az = jnp.moveaxis(q_a, -1, 0)
    bw, bx, by, bz = jnp.moveaxis(q_b, -1, 0)
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


@jax.jit
def quat_conjugate(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Conjugate ``(w, -x, -y, -z)``: the inverse of a unit quaternion."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


@jax.jit
def quat_rotate(
    q: Float[Array, "*batch 4"], v: Float[Array, "*batch 3"]
) -> Float[Array, "*batch 3"]:
    """Rotate vectors: ``R(q) v`` for unit quaternions q (wxyz), any length unit."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


@jax.jit
def quat_to_matrix(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of a unit quaternion (wxyz); ``x_a = R x_b``."""
    rows = rotation_rows(*jnp.moveaxis(q, -1, 0))
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def rotation_rows(w: ArrayLike, x: ArrayLike, y: ArrayLike, z: ArrayLike) -> list[list[ArrayLike]]:
    """Rotation matrix entries ``R[a][b]`` of unit quaternions given as separate arrays
    (jax or numpy: plain arithmetic, no compilation for numpy inputs)."""
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]


@jax.jit
def matrix_to_quat(matrix: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion (wxyz, ``w >= 0``) of a rotation matrix (Shepperd's method).

    Picks the largest of the four candidate denominators, so it is accurate for every
    rotation including 180°.
    """
    m = matrix
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    cand = jnp.stack([tr, m00, m11, m22], axis=-1)
    k = jnp.argmax(cand, axis=-1)
    # 4·q_k² for the chosen component; >= 1 for a rotation matrix, guarded anyway.
    d = jnp.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    dk = jnp.take_along_axis(d, k[..., None], axis=-1)[..., 0]
    s = jnp.sqrt(jnp.where(dk > 0, dk, 1.0))  # = 2 |q_k|
    q_w = jnp.stack(
        [
            s * s,
            m[..., 2, 1] - m[..., 1, 2],
            m[..., 0, 2] - m[..., 2, 0],
            m[..., 1, 0] - m[..., 0, 1],
        ],
        axis=-1,
    )
    q_x = jnp.stack(
        [
            m[..., 2, 1] - m[..., 1, 2],
            s * s,
            m[..., 0, 1] + m[..., 1, 0],
            m[..., 0, 2] + m[..., 2, 0],
        ],
        axis=-1,
    )
    q_y = jnp.stack(
        [
            m[..., 0, 2] - m[..., 2, 0],
            m[..., 0, 1] + m[..., 1, 0],
            s * s,
            m[..., 1, 2] + m[..., 2, 1],
        ],
        axis=-1,
    )
    q_z = jnp.stack(
        [
            m[..., 1, 0] - m[..., 0, 1],
            m[..., 0, 2] + m[..., 2, 0],
            m[..., 1, 2] + m[..., 2, 1],
            s * s,
        ],
        axis=-1,
    )
    cands = jnp.stack([q_w, q_x, q_y, q_z], axis=-2)  # (..., 4 choices, 4)
    q = jnp.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :] / (2.0 * s[..., None])
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)
