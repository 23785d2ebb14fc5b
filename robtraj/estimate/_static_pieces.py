"""The static frames of a recording for LED registration, read once and kept compactly.

Registration (`register_pieces`) passes over the frames where the tool stands still
several times (two per round of its algorithm). `static_pieces` reads them in cells
aligned with the pose passes' chunks, computes their paper LED variance there, and keeps
what registration looks at (the positions and variance of the LEDs each frame sees) in
memory within a fixed budget; frames beyond it are read and computed again in every pass.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np

from ..recording import FrameArray, finite_points
from ._chunks import CHUNK, chunk_length, slab
from ._pose_passes import variance_chunk
from ._registration import Piece, Pieces

_REGISTRATION_CELL = 8192  # frames per LED-variance call on the static frames
#: bytes of static frames (positions and LED variance) registration keeps between passes
REGISTRATION_CACHE_BYTES = 512 << 20


class _Kept:
    """Static frames kept between registration's passes, compactly: which LEDs each frame
    sees, and the positions and variance of those only (a frame sees about half of a
    tool's LEDs; registration looks at nothing else), in arrays allocated once, within
    `budget` bytes."""

    def __init__(self, frames: int, m: int, budget: int) -> None:
        self.frames, self.m = frames, m
        self.points = max(0, (budget - frames * m) // 32)
        self.seen: np.ndarray | None = None  # (frames, m)
        self.values: np.ndarray | None = None  # (points, 4): x, y, z, variance
        self.used = (0, 0)  # frames, points
        self.index: dict[int, tuple[int, int, int, int, int, int]] = {}

    def __contains__(self, i: int) -> bool:
        return i in self.index

    def add(self, i: int, piece: Piece) -> None:
        seen = finite_points(piece.positions)
        f, k = seen.shape[0], int(seen.sum())
        f0, p0 = self.used
        if p0 + k > self.points or f0 + f > self.frames:
            return
        if self.seen is None:
            self.seen = np.empty((self.frames, self.m), bool)
            self.values = np.empty((self.points, 4))
        self.seen[f0 : f0 + f] = seen
        self.values[p0 : p0 + k, :3] = piece.positions[seen]
        self.values[p0 : p0 + k, 3] = piece.variance[seen]
        self.index[i] = (piece.segment, piece.start, f0, f0 + f, p0, p0 + k)
        self.used = (f0 + f, p0 + k)

    def get(self, i: int) -> Piece:
        segment, start, f0, f1, p0, p1 = self.index[i]
        seen = self.seen[f0:f1]
        positions = np.full((f1 - f0, self.m, 3), np.nan)
        variance = np.full((f1 - f0, self.m), np.nan)
        positions[seen] = self.values[p0:p1, :3]
        variance[seen] = self.values[p0:p1, 3]
        return Piece(segment, start, positions, variance)


def static_pieces(
    source: FrameArray,
    segments: list[tuple[int, int]],
    window: int,
    chunk: int = CHUNK,
    cache_bytes: int | None = None,
) -> Pieces:
    """The static frames of `source` with their paper LED variance, for registration.

    The variance is computed on cells of frames aligned with the pose passes' chunks
    (a cell shared by consecutive segments once per pass). Registration passes over the
    static frames several times: the first pieces, up to `cache_bytes` (default
    `REGISTRATION_CACHE_BYTES`; an LED unseen in a frame as NaN, its variance NaN), are
    kept from the first pass; the others are read and computed again in every pass.
    """
    h = window // 2
    n, m = source.shape[:2]
    cell = min(_REGISTRATION_CELL, chunk_length(n, chunk))
    plan = [  # (segment, cell start, first frame, stop)
        (j, c0, max(a, c0), min(b, c0 + cell))
        for j, (a, b) in enumerate(segments)
        for c0 in range(a - a % cell, b, cell)
    ]
    budget = REGISTRATION_CACHE_BYTES if cache_bytes is None else cache_bytes
    kept = _Kept(sum(e - s for _, _, s, e in plan), m, budget)
    passes = [0]

    def compute(c0):
        x = slab(source, c0, cell, h, np.nan)
        return x[h : h + cell], variance_chunk(jax.device_put(x), window, ("paper",))

    def pieces() -> Iterator[Piece]:
        passes[0] += 1
        cells = list(dict.fromkeys(c0 for i, (_, c0, _, _) in enumerate(plan) if i not in kept))
        with ThreadPoolExecutor(max_workers=1) as pool:  # the next cell read ahead
            order = iter(cells)
            ahead = {}
            nxt = next(order, None)
            if nxt is not None:
                ahead[nxt] = pool.submit(compute, nxt)
            current = (None, None, None)
            for i, (j, c0, s, e) in enumerate(plan):
                if i in kept:
                    yield kept.get(i)
                    continue
                if current[0] != c0:
                    x, var = ahead.pop(c0).result()
                    nxt = next(order, None)
                    if nxt is not None:
                        ahead[nxt] = pool.submit(compute, nxt)
                    current = (c0, x, np.asarray(var)[0])
                piece = Piece(j, s, current[1][s - c0 : e - c0], current[2][s - c0 : e - c0])
                if passes[0] == 1:
                    kept.add(i, piece)
                yield piece

    return pieces
