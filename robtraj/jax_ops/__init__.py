"""Jit-compiled batched kernels: arrays in, arrays out, no I/O.

Dtype-generic (float32 works, e.g. on GPU); accept frame-sharded arrays. Imports
nothing else from robtraj. Quaternions are w, x, y, z.
"""

from ._led_variance import led_variance as led_variance, led_variances as led_variances
from ._procrustes import (
    RigidFit as RigidFit,
    collinear_threshold as collinear_threshold,
    weighted_procrustes as weighted_procrustes,
)
from ._quaternion import (
    matrix_to_quat as matrix_to_quat,
    quat_conjugate as quat_conjugate,
    quat_multiply as quat_multiply,
    quat_rotate as quat_rotate,
    quat_to_matrix as quat_to_matrix,
    rotation_rows as rotation_rows,
)
from ._rotation_angle import rotation_angle as rotation_angle
from ._se3_jacobian import se3_right_jacobian as se3_right_jacobian
from ._slerp import slerp as slerp
from ._windowed import windowed_moments as windowed_moments
