"""Static-segment detection from the tracker data alone (no robot log needed)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..recording import FrameArray
from ._chunks import CHUNK, over_frames


def static_segments(
    time: np.ndarray,
    positions: FrameArray,
    *,
    max_speed: float = 1e-3,
    lag: float = 0.2,
    min_duration: float = 0.3,
    visit: Callable[[int, np.ndarray], None] | None = None,
    chunk: int = CHUNK,
) -> list[tuple[int, int]]:
    """Frame ranges ``[start, stop)`` in which the LED tool stands still.

    The speed of each LED is its displacement over `lag` seconds; a frame is static when
    the median speed over the LEDs seen at both ends is below `max_speed` [m/s] on
    both sides of it. Runs shorter than `min_duration` [s] are dropped. Works on any
    active-LED recording (positions `(N, M, 3)` [m] with NaN for unseen: an array or a
    lazily read recording's, passed over in chunks). `visit(a, x)`, if given, sees every
    chunk of positions as it is read (frames ``a .. a + len(x) - 1``, each frame once), so
    a caller that needs another pass over them gets it in this one; `chunk` frames at a
    time.
    """
    n = time.shape[0]
    dt = float(np.median(np.diff(time))) if n >= 3 else 1.0
    k = max(1, int(round(lag / dt)))
    if n < 3 or k >= n:
        if visit is not None:
            over_frames(positions, visit, chunk)
        return []
    med = _median_displacement(positions, k, chunk, visit)
    slow = med / (k * dt) < max_speed  # window [t, t+k] is still
    static = np.zeros(n, bool)
    # frame t is static when the windows ending and starting at it are both still
    static[k:-k] = slow[: n - 2 * k] & slow[k:]
    static[:k] = slow[0]
    static[-k:] = slow[-1]
    edges = np.flatnonzero(np.diff(np.concatenate([[0], static.astype(np.int8), [0]])))
    runs = list(zip(edges[::2], edges[1::2]))
    min_frames = max(2, int(round(min_duration / dt)))
    return [(int(a), int(b)) for a, b in runs if b - a >= min_frames]


def _median_displacement(
    positions: FrameArray, k: int, chunk: int = CHUNK, visit: Callable | None = None
) -> np.ndarray:
    """`(N - k,)` median over the LEDs seen at both ends of each LED's displacement [m]
    from frame t to t + k (inf where none is), chunk by chunk."""
    n = positions.shape[0]
    med = np.full(n - k, np.inf)

    def median(a, x):
        x = np.asarray(x)
        if visit is not None:
            visit(a, x[: min(chunk, n - a)])
        if a >= n - k:
            return
        disp = np.linalg.norm(x[k:] - x[:-k], axis=-1)  # (frames, M), NaN if unseen
        with np.errstate(all="ignore"):
            ok = np.isfinite(disp).any(1)
            part = med[a : a + disp.shape[0]]
            part[ok] = np.nanmedian(disp[ok], axis=1)

    over_frames(positions, median, chunk, extra=k)
    return med
