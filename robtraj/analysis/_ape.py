"""Absolute pose error of time-aligned trajectories (what evo calls APE, no alignment)."""

from __future__ import annotations

import numpy as np
from jaxtyping import Float

from ._quat import rotation_angle


def absolute_pose_error(
    position: Float[np.ndarray, "frames 3"],
    quaternion_wxyz: Float[np.ndarray, "frames 4"],
    reference_position: Float[np.ndarray, "frames 3"],
    reference_quaternion_wxyz: Float[np.ndarray, "frames 4"],
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation error [m] and single rotation angle [rad] against a reference.

    Both trajectories are in the same frame and sampled at the same instants (no
    alignment); NaN where either pose is missing. The statistics of these arrays equal
    evo's APE with `translation_part` and `rotation_angle_rad`.
    """
    t = np.linalg.norm(np.asarray(position) - np.asarray(reference_position), axis=1)
    r = rotation_angle(np.asarray(reference_quaternion_wxyz), np.asarray(quaternion_wxyz))
    return t, r
