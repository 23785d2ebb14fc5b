"""Static-segment detection from the tracker data alone (no robot log needed)."""

from __future__ import annotations

import numpy as np


def static_segments(
    time: np.ndarray,
    positions: np.ndarray,
    *,
    max_speed: float = 1e-3,
    lag: float = 0.2,
    min_duration: float = 0.3,
) -> list[tuple[int, int]]:
    """Frame ranges ``[start, stop)`` in which the LED tool stands still.

    The speed of each LED is its displacement over `lag` seconds; a frame is static when
    the median speed over the LEDs seen at both ends is below `max_speed` [m/s] on
    both sides of it. Runs shorter than `min_duration` [s] are dropped. Works on any
    active-LED recording (positions `(N, M, 3)` [m] with NaN for unseen).
    """
    n = time.shape[0]
    if n < 3:
        return []
    dt = float(np.median(np.diff(time)))
    k = max(1, int(round(lag / dt)))
    if k >= n:
        return []
    disp = np.linalg.norm(positions[k:] - positions[:-k], axis=-1)  # (N-k, M), NaN if unseen
    with np.errstate(all="ignore"):
        ok = np.isfinite(disp).any(1)
        med = np.full(n - k, np.inf)
        med[ok] = np.nanmedian(disp[ok], axis=1)
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
