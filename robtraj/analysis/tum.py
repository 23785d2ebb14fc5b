"""TUM trajectory files: one pose per line, ``timestamp tx ty tz qx qy qz qw``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from jaxtyping import Float

from .._errors import UserError


def write_tum(
    path: str | os.PathLike,
    time: Float[np.ndarray, " frames"],
    position: Float[np.ndarray, "frames 3"],
    quaternion_wxyz: Float[np.ndarray, "frames 4"],
) -> Path:
    """Write poses as a TUM trajectory file (evo, the TUM RGB-D benchmark tools).

    **Arguments:**

    - `time` `(N,)` [s], `position` `(N, 3)` [m], `quaternion_wxyz` `(N, 4)` (written in the
      TUM order x, y, z, w). Frames with a NaN in position or orientation are skipped.

    **Returns:** the path written.
    """
    time = np.asarray(time, np.float64)
    position = np.asarray(position, np.float64)
    quaternion_wxyz = np.asarray(quaternion_wxyz, np.float64)
    if not (time.shape[0] == position.shape[0] == quaternion_wxyz.shape[0]):
        raise UserError(
            f"TUM export needs as many times ({time.shape[0]}) as positions "
            f"({position.shape[0]}) and orientations ({quaternion_wxyz.shape[0]})"
        )
    rows = np.column_stack([time, position, quaternion_wxyz[:, [1, 2, 3, 0]]])
    rows = rows[np.all(np.isfinite(rows), axis=1)]
    path = Path(path)
    np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")
    return path
