"""NumPy quaternion helpers for the analysis layer (w, x, y, z; batched over leading axes).

The analysis runs on NumPy/SciPy arrays of whole recordings (k-d trees, tables), so it
keeps its own small float64 versions of the `robtraj.jax_ops` rotation kernels.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def quat_normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product `a ⊗ b` (apply `b` first, then `a`)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def rotation_angle(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Single rotation angle [rad] of `q_a⁻¹ ⊗ q_b` (paper eq. 1–2), in `[0, π]`.

    # atan2 form: acos(w) or acos of the trace loses precision near 0.
    """
    rel = quat_multiply(quat_conjugate(q_a), q_b)
    return np.asarray(2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0])))


def slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation from `q0` (s=0) to `q1` (s=1) along the shorter arc."""
    s = np.asarray(s, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    n_minus = np.linalg.norm(q1 - q0, axis=-1, keepdims=True)
    n_plus = np.linalg.norm(q1 + q0, axis=-1, keepdims=True)
    theta = 2.0 * np.arctan2(n_minus, n_plus)  # angle between q0 and q1 in R^4, <= π/2
    # sin(aθ)/sinθ = a·sinc(aθ/π)/sinc(θ/π): no 0/0 for nearly equal quaternions
    denom = np.sinc(theta / np.pi)
    c0 = (1.0 - s) * np.sinc((1.0 - s) * theta / np.pi) / denom
    c1 = s * np.sinc(s * theta / np.pi) / denom
    return quat_normalize(c0 * q0 + c1 * q1)


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
