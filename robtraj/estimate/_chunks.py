"""Passes over the frames of a recording, chunk by chunk.

Every estimation step that touches all frames reads them here in chunks of `CHUNK`
frames (with a halo where a window needs it) from a per-frame source: an in-memory NumPy
array, whose slices are free, or a recording opened lazily (`robtraj.open_recording`),
whose slices are read from the file. Memory is that of a chunk, whatever the length of
the recording; one code path for both.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..recording import FrameArray, finite_points

CHUNK = 65536  # frames per kernel call: bounded memory on whole recordings


class Columns:
    """The LED columns `cols` (all if None) of a per-frame source `(N, M, 3)` as float64
    `(N, K, 3)`: ``x[a:b]`` reads frames ``a..b-1`` of those columns."""

    def __init__(self, source: FrameArray, cols: np.ndarray | None = None) -> None:
        self.source = source
        n, m = source.shape[:2]
        self.cols = None if cols is None or np.array_equal(cols, np.arange(m)) else cols
        k = m if self.cols is None else len(self.cols)
        self.shape = (n, k, *source.shape[2:])
        self.dtype = np.dtype(np.float64)

    def __getitem__(self, frames: slice) -> np.ndarray:
        if not isinstance(frames, slice):
            raise TypeError("Columns are read by frame slices")
        x = np.asarray(self.source[frames], np.float64)
        return x if self.cols is None else x[:, self.cols]


class Scaled:
    """A per-frame source `(N, …)` divided by `by` as it is read (float64): ``x[a:b]``."""

    def __init__(self, source: FrameArray, by: float) -> None:
        self.source, self.by = source, float(by)
        self.shape = tuple(source.shape)
        self.dtype = np.dtype(np.float64)

    def __getitem__(self, frames: slice) -> np.ndarray:
        return np.asarray(self.source[frames], np.float64) / self.by


def chunk_length(n: int, chunk: int = CHUNK) -> int:
    """Frames per kernel call: `chunk`, or for shorter recordings the next power of two
    (at least 4096), so the kernels are compiled for a few shapes only."""
    if n >= chunk:
        return chunk
    return min(chunk, max(4096, 1 << (n - 1).bit_length()))


def slab(arr: FrameArray, start: int, size: int, halo: int, fill) -> np.ndarray:
    """``arr[start - halo : start + size + halo]`` with `fill` beyond the ends: always
    ``size + 2·halo`` frames, so every chunk has the same shape."""
    lo, hi = start - halo, start + size + halo
    out = np.full((hi - lo, *arr.shape[1:]), fill, arr.dtype)
    s, e = max(lo, 0), min(hi, arr.shape[0])
    if e > s:
        out[s - lo : e - lo] = arr[s:e]
    return out


def over_chunks(n: int, size: int, prepare: Callable, compute: Callable, collect: Callable):
    """Run a kernel over the chunks ``[a, a + size)`` of n frames as a pipeline.

    `prepare(a)` (reading, padding, host-to-device copy) runs on a worker thread one
    chunk ahead; `compute(*args)` is dispatched asynchronously, and the previous chunk's
    result is fetched by `collect(a, result)` while the device works on the next one.
    Chunks are collected in order.
    """
    starts = list(range(0, n, size))
    if not starts:
        return
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(prepare, starts[0])
        pending = None
        try:
            for i, a in enumerate(starts):
                args = ahead.result()
                if i + 1 < len(starts):
                    ahead = pool.submit(prepare, starts[i + 1])
                result = compute(*args)
                if pending is not None:
                    collect(*pending)
                pending = (a, result)
            collect(*pending)
        finally:
            ahead.cancel()


def over_frames(source: FrameArray, visit: Callable, chunk: int = CHUNK, extra: int = 0) -> None:
    """`visit(a, x)` for the chunks ``[a, a + chunk)`` of `source` in order, ``x`` holding
    frames ``a .. a + chunk + extra - 1`` (fewer at the end), read one chunk ahead on a
    worker thread."""
    n = source.shape[0]

    def prepare(a):
        return (source[a : min(n, a + chunk + extra)],)

    over_chunks(n, chunk, prepare, lambda x: x, visit)


def visible_frames(source: FrameArray, chunk: int = CHUNK) -> np.ndarray:
    """`(N, M)` bool: the point `(N, M, 3)` of `source` finite in that frame (as
    `Recording.visible`), read chunk by chunk."""
    out = np.empty(source.shape[:2], bool)

    def visit(a, x):
        out[a : a + x.shape[0]] = finite_points(x)

    over_frames(source, visit, chunk)
    return out
