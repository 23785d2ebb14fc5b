"""TUM trajectory files: one pose per line, ``timestamp tx ty tz qx qy qz qw``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from jaxtyping import Bool, Float

from .._errors import UserError

#: frames formatted at a time: the text of a long trajectory is written block by block
ROWS = 1 << 16


def write_tum(
    path: str | os.PathLike,
    time: Float[np.ndarray, " frames"],
    position: Float[np.ndarray, "frames 3"],
    quaternion_wxyz: Float[np.ndarray, "frames 4"],
    keep: Bool[np.ndarray, " frames"] | None = None,
) -> Path:
    """Write poses as a TUM trajectory file (evo, the TUM RGB-D benchmark tools).

    **Arguments:**

    - `time` `(N,)` [s], `position` `(N, 3)` [m], `quaternion_wxyz` `(N, 4)` (written in the
      TUM order x, y, z, w). Frames with a NaN in position or orientation are skipped.
    - `keep` `(N,)`: write only these frames (all when None).

    **Returns:** the path written.
    """
    n = np.shape(time)[0]
    if not (n == np.shape(position)[0] == np.shape(quaternion_wxyz)[0]):
        raise UserError(
            f"TUM export needs as many times ({n}) as positions "
            f"({np.shape(position)[0]}) and orientations ({np.shape(quaternion_wxyz)[0]})"
        )
    path = Path(path)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for a in range(0, n, ROWS):
            b = min(n, a + ROWS)
            rows = np.column_stack(
                [
                    np.asarray(time[a:b], np.float64),
                    np.asarray(position[a:b], np.float64),
                    np.asarray(quaternion_wxyz[a:b], np.float64)[:, [1, 2, 3, 0]],
                ]
            )
            use = np.all(np.isfinite(rows), axis=1)
            if keep is not None:
                use &= np.asarray(keep[a:b], bool)
            np.savetxt(f, rows[use], fmt="%.9f")
    return path
