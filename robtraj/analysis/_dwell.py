"""Test poses and cycles from the program, attained poses from stationary measured segments."""

from __future__ import annotations

import dataclasses

import numpy as np

from ._quat import mean_quaternion, rotation_angle


def cluster_targets(
    position: np.ndarray, quaternion_wxyz: np.ndarray, tol: float, angle_tol: float
) -> np.ndarray:
    """`(P,)` cluster id per program target: same position (within `tol` [m]) and orientation
    (within `angle_tol` [rad]) means the same pose. Ids in order of first appearance."""
    ids = np.full(position.shape[0], -1, np.int64)
    reps: list[int] = []
    for i in range(position.shape[0]):  # P is small (targets, not frames)
        for c, r in enumerate(reps):
            if (
                np.linalg.norm(position[i] - position[r]) <= tol
                and rotation_angle(quaternion_wxyz[i], quaternion_wxyz[r]) <= angle_tol
            ):
                ids[i] = c
                break
        else:
            ids[i] = len(reps)
            reps.append(i)
    return ids


def smoothed_speed(
    time: np.ndarray, position: np.ndarray, window: float, block: int = 1 << 16
) -> np.ndarray:
    """TCP speed [m/s] by central differences over ±`window`/2 seconds (NaN frames
    skipped), `block` seen frames at a time."""
    rows = np.flatnonzero(np.all(np.isfinite(position), axis=1))
    speed = np.full(time.shape[0], np.nan)
    if rows.size < 2:
        return speed
    t, last = time[rows], rows.size - 1
    for a in range(0, rows.size, block):
        tb = t[a : a + block]
        lo = np.searchsorted(t, tb - window / 2, side="left")
        hi = np.clip(np.searchsorted(t, tb + window / 2, side="right") - 1, 0, last)
        lo = np.minimum(lo, hi - 1).clip(0)
        hi = np.maximum(hi, lo + 1).clip(max=last)
        dt = t[hi] - t[lo]
        step = position[rows[hi]] - position[rows[lo]]
        speed[rows[a : a + block]] = np.linalg.norm(step, axis=1) / np.where(dt > 0, dt, np.inf)
    return speed


@dataclasses.dataclass(frozen=True)
class Dwell:
    """A stationary stretch of the measurement: frames `[start, stop)`, the attained pose
    (mean over its second half, after stabilisation) and the program target it belongs to."""

    start: int
    stop: int
    position: np.ndarray
    quaternion_wxyz: np.ndarray
    target: int


def find_dwells(
    time: np.ndarray,
    position: np.ndarray,
    quaternion_wxyz: np.ndarray,
    target_position: np.ndarray,
    segment: np.ndarray | None,
    *,
    speed_threshold: float,
    min_duration: float,
    speed_window: float,
    match_radius: float,
) -> list[Dwell]:
    """Stationary segments (speed below `speed_threshold` for at least `min_duration`),
    each assigned to the nearest program target (among the frame's segment and the one
    before it when `segment` is given) within `match_radius`."""
    speed = smoothed_speed(time, position, speed_window)
    still = np.nan_to_num(speed, nan=np.inf) < speed_threshold
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    dwells = []
    for a, b in zip(starts, stops):  # one iteration per dwell, not per frame
        if time[b - 1] - time[a] < min_duration:
            continue
        half = slice(a + (b - a) // 2, b)
        ok = np.all(np.isfinite(position[half]), axis=1)
        if not np.any(ok):
            continue
        p = position[half][ok].mean(axis=0)
        q = mean_quaternion(quaternion_wxyz[half][ok])
        if segment is not None:
            seg = int(segment[a + (b - a) // 2])
            cands = np.array([c for c in (seg - 1, seg, seg + 1) if 0 <= c < len(target_position)])
        else:
            cands = np.arange(len(target_position))
        d = np.linalg.norm(target_position[cands] - p, axis=1)
        if d.size == 0 or d.min() > match_radius:
            continue
        dwells.append(Dwell(int(a), int(b), p, q, int(cands[np.argmin(d)])))
    return dwells
