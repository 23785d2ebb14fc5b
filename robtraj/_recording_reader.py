"""A recording read lazily: the large per-frame tracker datasets stay in the open file and
are read by frame ranges (`open_recording`), so a pass over a recording of any length
holds one chunk of it at a time.

Everything else is read and validated as `read_recording` does (`read_deferred`: the
same checks, on the shapes of the datasets left in the file), including the trimming of a
file whose recorder was killed while flushing.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ._errors import UserError
from .recording import DEFERRABLE, FrameArray, Recording, read_deferred

__all__ = ["FrameArray", "LazyFrames", "open_recording"]


class _File:
    """The open HDF5 file behind a lazy recording; reopened in SWMR mode when a plain read
    fails (a recorder killed mid-flush leaves chunks beyond the end-of-file address in its
    superblock, which plain reads refuse; see `read_recording`)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.swmr = False
        try:
            self.f = h5py.File(path, "r")
        except OSError as e:
            try:  # a SWMR writer killed (earlier recorders) leaves its flag set
                self.f = h5py.File(path, "r", swmr=True)
                self.swmr = True
            except OSError:
                raise UserError(f"{path}: not a readable HDF5 file ({_one_line(e)})") from None

    def reopen_swmr(self) -> bool:
        """Switch to SWMR reading; False if it already was (or cannot be)."""
        if self.swmr:
            return False
        try:
            f = h5py.File(self.path, "r", swmr=True)
        except OSError:
            return False
        self.f.close()
        self.f, self.swmr = f, True
        return True

    def close(self) -> None:
        self.f.close()


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


class LazyFrames:
    """A per-frame dataset of an open recording (`open_recording`), read on demand.

    `shape`, `dtype`, `ndim` and `len` as the array's; ``x[a:b]`` (optionally with more
    indices after the frame slice, ``x[a:b, k]``) reads those frames from the file as a
    NumPy array; ``x[i]`` one frame; any other index, and ``np.asarray(x)``, read the whole
    dataset. A frame range HDF5 cannot decode (corrupted or truncated data) raises a
    one-line `UserError` naming the first unreadable chunk's frames.
    """

    def __init__(self, file: _File, key: str, n_frames: int) -> None:
        ds = file.f[key]
        self._file = file
        self._key = key
        self._chunk = int(ds.chunks[0]) if ds.chunks else max(1, int(n_frames))
        self.shape: tuple[int, ...] = (int(n_frames), *ds.shape[1:])
        self.dtype = ds.dtype

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"LazyFrames({self._file.path}:{self._key}, shape={self.shape}, dtype={self.dtype})"

    def __getitem__(self, key: Any) -> np.ndarray:
        first, rest = (key[0], key[1:]) if isinstance(key, tuple) else (key, ())
        if isinstance(first, slice):
            a, b, step = first.indices(self.shape[0])
            if step == 1:
                data = self.read(a, max(a, b))
            else:
                lo, hi = (a, b) if step > 0 else (b + 1, a + 1)
                data = self.read(lo, max(lo, hi))[slice(a - lo, None if b < lo else b - lo, step)]
        elif isinstance(first, int | np.integer):
            i = int(first) + (self.shape[0] if first < 0 else 0)
            if not 0 <= i < self.shape[0]:
                raise IndexError(f"frame {int(first)} out of range for {self.shape[0]} frames")
            data = self.read(i, i + 1)[0]
            return data[rest] if rest else data
        else:
            return np.asarray(self)[key]
        return data[(slice(None), *rest)] if rest else data

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        data = self.read(0, self.shape[0])
        return data if dtype is None else data.astype(dtype, copy=False)

    def read(self, a: int, b: int) -> np.ndarray:
        """Frames ``a..b-1`` (``0 <= a <= b <= len``) as a NumPy array."""
        try:
            return self._file.f[self._key][a:b]
        except (OSError, RuntimeError) as e:
            error = e
        if self._file.reopen_swmr():
            try:
                return self._file.f[self._key][a:b]
            except (OSError, RuntimeError) as e:
                error = e
        raise self._unreadable(a, b, error)

    def _unreadable(self, a: int, b: int, error: BaseException) -> UserError:
        """The error for frames ``a..b-1``, naming the first chunk that does not decode."""
        ds, c = self._file.f[self._key], self._chunk
        lo, hi = a, b - 1
        for start in range(a - a % c, b, c):
            s, e = max(start, a), min(start + c, b)
            try:
                ds[s:e]
            except (OSError, RuntimeError) as bad:
                lo, hi, error = start, min(start + c, self.shape[0]) - 1, bad
                break
        return UserError(
            f"{self._file.path}: frames {lo}–{hi} of {self._key} are unreadable "
            f"({_one_line(error)})"
        )


@contextlib.contextmanager
def open_recording(path: str | os.PathLike, *, truth: bool = True) -> Iterator[Recording]:
    """Open a schema-1 recording for reading by frame ranges; yields its `Recording`.

    As `read_recording` (the same checks and messages), except that `positions` and
    `status` are `LazyFrames` read from the file on demand: valid until the ``with``
    block ends, which closes the file. Everything else is read into memory, except a
    simulation's /truth without `truth` (``truth=None``: commands that never compare
    with it).

    !!! Example

        ```python
        with open_recording("REC.h5") as rec:
            first = rec.positions[:1000]  # (1000, M, 3) float64
        ```
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    name = str(path)
    file = _File(path)
    try:
        rec = _read_lazy(file, name, truth)
        yield rec
    finally:
        file.close()


def _read_lazy(file: _File, name: str, truth: bool = True) -> Recording:
    """`read_deferred` with the per-frame tracker datasets as `LazyFrames` (the bulk of a
    recording: `(N, M, 3)` positions and `(N, M)` status)."""
    wrap = {k: (lambda ds, n, key=key: LazyFrames(file, key, n)) for k, key in DEFERRABLE.items()}
    try:
        return read_deferred(file.f, name, wrap, truth=truth)
    except OSError as e:
        if not file.reopen_swmr():
            raise UserError(f"{file.path}: unreadable HDF5 data ({_one_line(e)})") from None
    try:
        return read_deferred(file.f, name, wrap, truth=truth)
    except OSError as e:
        raise UserError(f"{file.path}: unreadable HDF5 data ({_one_line(e)})") from None
