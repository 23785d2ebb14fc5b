"""Every state a kill can leave while `RecordingAppender` flushes: the file after each
prefix of the flush's writes, and with each write torn in half. Plain h5py opens every
one, and `read_recording` reads at least the frames of the previous flush, exactly."""

from __future__ import annotations

import io

import h5py
import numpy as np
import pytest

from robtraj import UserError
from robtraj.recording import RecordingAppender, read_recording

M = 5


class _WriteLog(io.RawIOBase):
    """A file for h5py's "fileobj" driver that keeps every write and truncation in order."""

    def __init__(self, path) -> None:
        self._f = open(path, "r+b")  # noqa: SIM115 - closed by close()
        self.ops: list[tuple[int, bytes | None]] = []  # (offset, data) or (size, None)

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def readinto(self, b) -> int:
        return self._f.readinto(b)

    def write(self, b) -> int:
        self.ops.append((self._f.tell(), bytes(b)))
        return self._f.write(b)

    def truncate(self, size: int | None = None) -> int:
        size = self._f.tell() if size is None else size
        self.ops.append((size, None))
        return self._f.truncate(size)

    def flush(self) -> None:
        if not self._f.closed:
            self._f.flush()

    def close(self) -> None:
        self._f.close()
        super().close()


class _Logged(RecordingAppender):
    """Each flush's file opened through a `_WriteLog`, kept in `last_log`."""

    def _open(self) -> h5py.File:
        self.last_log = _WriteLog(self.path)
        return h5py.File(self.last_log, "r+")

    def flush(self) -> None:
        super().flush()
        self.last_log.close()


def _crash_states(before: bytes, ops):
    """The file as a kill can leave it: after each write, and halfway through each."""
    buf = bytearray(before)
    for offset, data in ops:
        if data is None:
            del buf[offset:]
            yield bytes(buf)
            continue
        for part in (data[: len(data) // 2], data):
            state = bytearray(buf)
            state[len(state) : offset] = bytes(max(0, offset - len(state)))
            state[offset : offset + len(part)] = part
            yield bytes(state)
        buf = state


def _frames(n: int):
    rng = np.random.default_rng(3)
    pos = rng.normal(size=(n, M, 3))
    status = rng.integers(0, 4, (n, M)).astype(np.uint8)
    pos[status == 1] = np.nan
    temp = (24.0 + rng.normal(size=n)).astype(np.float32)
    return 0.25 + np.arange(n) / 1000.0, np.arange(n, dtype=np.uint64) + 7, pos, status, temp


def _enumerate(tmp_path, app: _Logged, frames, batches, start: int = 0) -> int:
    """Append `batches` from frame `start`, checking every crash state of every flush."""
    state_path = tmp_path / "state.h5"
    n = start
    checked = 0
    for k in batches:
        before = app.path.read_bytes()
        app.append(*(a[n : n + k] for a in frames))
        app.flush()
        for state in _crash_states(before, app.last_log.ops):
            state_path.write_bytes(state)
            h5py.File(state_path, "r").close()  # plain h5py, no SWMR, no h5clear
            rec = read_recording(state_path)
            got = rec.n_frames
            assert n <= got <= n + k, (n, k, got)
            for want, have in zip(
                frames, (rec.time, rec.frame_index, rec.positions, rec.status, rec.temperature)
            ):
                assert want[:got].tobytes() == have.tobytes()
            checked += 1
        n += k
    return checked


# a first flush, chunks (1000 frames) filled from their middle, several chunks at once
BATCHES = [600, 500, 1, 1700, 2300, 5]


@pytest.mark.parametrize("compression", ["gzip", "lzf", None])
def test_every_crash_state_of_a_flush_keeps_the_previous_flush(tmp_path, compression):
    frames = _frames(sum(BATCHES))
    app = _Logged(tmp_path / "rec.h5", np.arange(M), compression=compression)
    checked = _enumerate(tmp_path, app, frames, BATCHES)
    app.close()
    assert checked > 100
    assert read_recording(app.path).n_frames == sum(BATCHES)


@pytest.mark.xfail(
    strict=True,
    raises=UserError,  # unreadable HDF5 data (wrong B-tree signature)
    reason="a flush that splits a node of a chunk index (v1 B-tree, 64 entries) writes the "
    "parent node before the new node: a kill between those two writes breaks the index",
)
def test_a_flush_splitting_a_chunk_index_node_is_not_covered(tmp_path):
    frames = _frames(64_500)
    app = _Logged(tmp_path / "rec.h5", np.arange(M), compression="gzip")
    app.append(*(a[:63_900] for a in frames))
    app.flush()
    try:
        _enumerate(tmp_path, app, frames, [600], start=63_900)
    finally:
        app.close()
