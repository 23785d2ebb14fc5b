"""NumPy quaternion helpers for the analysis layer (w, x, y, z; batched over leading axes).

The analysis runs on NumPy/SciPy arrays of whole recordings (k-d trees, tables); these
wrap the `robtraj.jax_ops` kernels with NumPy in and out.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from .. import jax_ops as _ops


def quat_normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    return np.asarray(_ops.quat_conjugate(jnp.asarray(q)))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product `a ⊗ b` (apply `b` first, then `a`)."""
    a, b = np.broadcast_arrays(a, b)
    return np.asarray(_ops.quat_multiply(jnp.asarray(a), jnp.asarray(b)))


def rotation_angle(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Single rotation angle [rad] of `q_a⁻¹ ⊗ q_b` (paper eq. 1–2), in `[0, π]`."""
    q_a, q_b = np.broadcast_arrays(q_a, q_b)
    return np.asarray(_ops.rotation_angle(jnp.asarray(q_a), jnp.asarray(q_b)))


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation from `q0` (s=0) to `q1` (s=1) along the shorter arc."""
    s = np.asarray(s, dtype=np.float64)
    q0, q1 = np.broadcast_arrays(q0, q1)
    shape = np.broadcast_shapes(q0.shape[:-1], s.shape)
    q0, q1 = np.broadcast_to(q0, (*shape, 4)), np.broadcast_to(q1, (*shape, 4))
    return np.asarray(
        _ops.slerp(jnp.asarray(q0), jnp.asarray(q1), jnp.asarray(np.broadcast_to(s, shape)))
    )


def to_rotation(q_wxyz: np.ndarray) -> Rotation:
    return Rotation.from_quat(np.asarray(q_wxyz)[..., [1, 2, 3, 0]])


def from_rotation(r: Rotation) -> np.ndarray:
    return r.as_quat()[..., [3, 0, 1, 2]]


def error_components(q_commanded: np.ndarray, q_attained: np.ndarray) -> np.ndarray:
    """ISO 9283 orientation components `(…, 3)` = (a, b, c) [rad] of the attained pose.

    The error rotation in the base frame, `R_attained · R_commandedᵀ`, written as
    extrinsic x-y-z angles: rotations about the base x, y and z axes. For the small
    errors of a robot these equal the coordinate-wise differences of the a, b, c angles
    the standard uses, but do not depend on where the commanded pose sits on the
    Euler-angle chart.
    """
    r = to_rotation(q_attained) * to_rotation(q_commanded).inv()
    return r.as_euler("xyz")


def mean_quaternion(q_wxyz: np.ndarray) -> np.ndarray:
    """Chordal L2 mean rotation of `(n, 4)` quaternions (sign-invariant)."""
    return from_rotation(to_rotation(q_wxyz).mean())
