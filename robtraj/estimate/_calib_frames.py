"""The tracker frames of a bundle fit, read block by block (`TrackerFrames`).

A fit passes over its frames once per solver step. They are never held whole: each pass
reads blocks of `BLOCK_FRAMES` frames from the recording (in memory, or opened lazily
with `robtraj.open_recording`), one block ahead on a worker thread, and builds the
kernels' `Frames` of each from compact per-frame state (time, drift, motion signs, the
cached flange poses) and the fit's weights, recomputed per block (`Weights`). Memory is
that of a block plus a few bytes per frame and LED, whatever the recording's length; the
same code path serves recordings in memory.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from ..recording import FrameArray, finite_points
from ._chunks import over_chunks

#: frames per block read from the recording (a whole number of kernel chunks)
BLOCK_FRAMES = 16384


@dataclasses.dataclass(frozen=True, eq=False)
class Weights:
    """The weights [1/m²] of a fit's observations, per block of frames: the user's
    (`user`, recording-shaped), else the noise model's inverse variances (`noise`, an
    `ObservationVariance`), else 1 where seen; times `factor` `(frames, leds)` (a robust
    loss's IRLS weights) where given; zero where unseen or not finite."""

    user: np.ndarray | None = None
    noise: object | None = None
    factor: np.ndarray | None = None

    def at(
        self, rows: np.ndarray, x: np.ndarray, columns: np.ndarray, a: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Weights `(len(rows), leds)` of recording frames `rows` (the fit's frames
        ``a ..``) whose positions are `x` `(len(rows), recording LEDs, 3)`, for the fit's
        LED `columns`: with `factor`, and without (the noise model's)."""
        seen = finite_points(x[:, columns])
        if self.user is not None:
            w = np.asarray(self.user[rows], float)[:, columns]
        elif self.noise is not None:
            with np.errstate(divide="ignore"):
                var = self.noise.at(rows, x)[:, columns]
                w = np.where(np.isfinite(var), 1.0 / var, 0.0)
        else:
            w = seen.astype(float)
        w = np.where(seen & np.isfinite(w) & (w > 0), w, 0.0)
        if self.factor is None:
            return w, w
        return w * self.factor[a : a + len(rows)], w


@dataclasses.dataclass(frozen=True, eq=False)
class Block:
    """One block of frames as the kernels read it (NumPy, `(chunks, chunk, ...)`, the
    last block padded with frames of weight zero) with its range ``[a, b)`` of the fit's
    frames and, unpadded, their weights (`noise`: without a robust loss's factor)."""

    a: int
    b: int
    frames: dict[str, np.ndarray]
    weights: np.ndarray
    noise: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class TrackerFrames:
    """The fit's tracker frames (module docstring): the recording's `positions` and the
    fit's LED `columns` in it, the recording frame of each fit frame (`frame` `(n,)`),
    per frame the tracker time [s], the drift variable, the motion signs `(n, joints)`
    (int8: −1, 0, 1), the cached base←flange poses `(n, 7)` (None while every step
    re-runs the kinematics), the `weights`, and the kernels' chunk length `size` and
    chunks per block `per`."""

    positions: FrameArray
    columns: np.ndarray
    frame: np.ndarray
    time: np.ndarray
    drift: np.ndarray
    direction: np.ndarray
    moving: np.ndarray
    weights: Weights
    size: int
    per: int
    base_from_flange: np.ndarray | None = None
    #: blocks kept between passes, for a recording in memory only (`blocks`)
    _kept: dict = dataclasses.field(default_factory=dict, init=False, repr=False)

    @property
    def n_frames(self) -> int:
        return int(self.frame.shape[0])

    @property
    def n_leds(self) -> int:
        return int(self.columns.shape[0])

    @property
    def block_frames(self) -> int:
        return self.size * self.per

    @property
    def n_blocks(self) -> int:
        return -(-self.n_frames // self.block_frames)

    @property
    def n_chunks(self) -> int:
        """Chunks of all blocks, padding included."""
        return self.n_blocks * self.per

    def replace(self, **changes) -> TrackerFrames:
        return dataclasses.replace(self, **changes)

    def read(self, a: int, b: int) -> np.ndarray:
        """Positions `(b − a, recording LEDs, 3)` [m] of the fit's frames ``a..b-1``,
        NaN where unseen."""
        return read_rows(self.positions, self.frame[a:b])

    def block(self, i: int, x: np.ndarray | None = None) -> Block:
        """Block `i` (positions `x` of its frames if already read)."""
        a = i * self.block_frames
        b = min(self.n_frames, a + self.block_frames)
        x = self.read(a, b) if x is None else x
        w, base = self.weights.at(self.frame[a:b], x, self.columns, a)
        xs = x[:, self.columns]
        seen = finite_points(xs)
        pad = self.block_frames - (b - a)

        def padded(v, fill_last=True):
            v = np.asarray(v)
            if pad:
                tail = np.repeat(v[-1:], pad, 0) if fill_last else np.zeros((pad, *v.shape[1:]))
                v = np.concatenate([v, tail])
            return v.reshape(self.per, self.size, *v.shape[1:])

        bff = self.base_from_flange
        frames = {
            "time": padded(self.time[a:b]),
            "direction": padded(self.direction[a:b].astype(np.float64)),
            "moving": padded(self.moving[a:b].astype(np.float64)),
            "drift": padded(self.drift[a:b]),
            "measured": padded(np.where(seen[..., None], xs, 0.0), fill_last=False),
            "sqrt_weight": padded(np.sqrt(w), fill_last=False),
            "base_from_flange": padded(bff[a:b])
            if bff is not None
            else np.zeros((self.per, self.size, 7)),
        }
        return Block(a, b, frames, w, base)

    def blocks(
        self,
        compute: Callable[[Block], object],
        collect: Callable[[Block, object], None] | None = None,
        read: bool = True,
    ) -> None:
        """`compute(block)` for every block in order, the next block read and prepared
        on a worker thread meanwhile; `collect(block, result)` of the previous block
        while the next one computes. Without `read`, the positions are not read (every
        LED unseen). A recording in memory keeps its blocks from one pass to the next
        (as much memory again as its positions); one read from a file is read again at
        every pass, so that memory does not grow with its length."""
        keep = self._kept if read and isinstance(self.positions, np.ndarray) else None

        def prepare(a):
            i = a // self.block_frames
            if keep is not None and i in keep:
                return (keep[i],)
            if read:
                block = self.block(i)
            else:
                b = min(self.n_frames, a + self.block_frames)
                block = self.block(i, np.full((b - a, *self.positions.shape[1:]), np.nan))
            if keep is not None:
                keep[i] = block
            return (block,)

        def run(block):
            return block, compute(block)

        def done(_a, result):
            if collect is not None:
                collect(*result)

        over_chunks(self.n_frames, self.block_frames, prepare, run, done)


def read_rows(source: FrameArray, rows: np.ndarray) -> np.ndarray:
    """``source[rows]`` for increasing `rows`, read by frame ranges: one range where the
    rows are dense, pieces no longer than the row count (or 4096) where they are not."""
    if rows.size == 0:
        return np.zeros((0, *source.shape[1:]))
    lo, hi = int(rows[0]), int(rows[-1]) + 1
    if hi - lo == rows.size:
        return np.asarray(source[lo:hi], np.float64)
    span = max(rows.size, 4096)
    if hi - lo <= 2 * span:
        return np.asarray(source[lo:hi], np.float64)[rows - lo]
    parts = []
    window = (rows - lo) // span
    cuts = np.flatnonzero(np.diff(window)) + 1
    for piece in np.split(rows, cuts):
        a, b = int(piece[0]), int(piece[-1]) + 1
        parts.append(np.asarray(source[a:b], np.float64)[piece - a])
    return np.concatenate(parts)
