"""Write a schema-1 recording chunk by chunk, as it is generated (`RecordingWriter`).

The file is the one `write_recording` writes for the whole recording: the same groups,
attributes and frame-independent datasets (`write_recording` writes them), the per-frame
datasets chunked along time, resizable and compressed alike. Only the frames being
appended are ever in memory.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import h5py
import numpy as np

from ._errors import UserError
from .recording import TRACKER_CHUNK_FRAMES, Pose, Recording, write_recording

#: the per-frame datasets of a recording (DESIGN section 4), in the order they are written
FRAME_DATASETS = (
    "tracker/time",
    "tracker/frame_index",
    "tracker/positions",
    "tracker/status",
    "tracker/temperature",
    "program/segment",
    "truth/tool_pose/position",
    "truth/tool_pose/quaternion_wxyz",
)


def frame_arrays(rec: Recording) -> dict[str, np.ndarray]:
    """The per-frame arrays `rec` holds, by dataset (`FRAME_DATASETS`; optional ones it
    lacks are left out)."""
    arrays = {
        "tracker/time": rec.time,
        "tracker/frame_index": rec.frame_index,
        "tracker/positions": rec.positions,
        "tracker/status": rec.status,
        "tracker/temperature": rec.temperature,
        "program/segment": None if rec.program is None else rec.program.segment,
        "truth/tool_pose/position": None if rec.truth is None else rec.truth.tool_pose.position,
        "truth/tool_pose/quaternion_wxyz": (
            None if rec.truth is None else rec.truth.tool_pose.quaternion_wxyz
        ),
    }
    return {k: np.asarray(a) for k, a in arrays.items() if a is not None}


def with_frame_arrays(rec: Recording, arrays: dict[str, np.ndarray]) -> Recording:
    """`rec` with its per-frame arrays replaced by `arrays` (as `frame_arrays` gives them)."""
    rec = rec.replace(
        time=arrays["tracker/time"],
        frame_index=arrays["tracker/frame_index"],
        positions=arrays["tracker/positions"],
        status=arrays.get("tracker/status"),
        temperature=arrays.get("tracker/temperature"),
    )
    if rec.program is not None:
        program = dataclasses.replace(rec.program, segment=arrays.get("program/segment"))
        rec = rec.replace(program=program)
    if rec.truth is not None:
        pose = Pose(arrays["truth/tool_pose/position"], arrays["truth/tool_pose/quaternion_wxyz"])
        rec = rec.replace(truth=dataclasses.replace(rec.truth, tool_pose=pose))
    return rec


class RecordingWriter:
    """Write a recording of `n_frames` frames to `path` while its frames are generated.

    `header` holds everything but the frames: its per-frame arrays have no frames
    (shape ``(0, ...)``, the dtype and trailing shape of the recording's), a None
    optional one leaves that dataset out. `append` adds frames in order; the file is
    written under a temporary name beside `path` and renamed into place when the
    ``with`` block ends with all `n_frames` appended, so a failure (or Ctrl-C) leaves no
    file under `path` and a file already there as it was; an existing `path` is refused
    (`UserError`) unless `overwrite`. The file reads back (`read_recording`) as
    `write_recording` of the whole recording writes it.

    Frames are written whole HDF5 chunks at a time (the frames of an incomplete chunk
    wait for the next `append`), so no chunk is compressed twice.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        header: Recording,
        n_frames: int,
        *,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise UserError(
                f"{self.path} exists; refusing to overwrite it (use --force or another name)"
            )
        self.n_frames = int(n_frames)
        self.written = 0
        self._last_time: float | None = None
        self._header = header
        self._keys = tuple(frame_arrays(header))
        self._tail: dict[str, np.ndarray] = {}
        self._tmp = self.path.with_name(f".{self.path.name}.tmp-{os.getpid()}")
        self._f: h5py.File | None = None

    def __enter__(self) -> RecordingWriter:
        self._tmp.unlink(missing_ok=True)
        try:
            # the schema's writer lays out the file (and checks the header); its per-frame
            # datasets, empty, are then replaced by resizable ones like those it makes
            write_recording(self._header, self._tmp, overwrite=True)
            self._f = h5py.File(self._tmp, "r+")
            self._create()
        except BaseException:
            self._abandon()
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self._abandon()
            return
        try:
            self._flush_tail()
            if self.written != self.n_frames:
                raise ValueError(f"{self.written} frames appended, expected {self.n_frames}")
            self._f.close()
            os.replace(self._tmp, self.path)
        finally:
            self._abandon()

    def _abandon(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
        self._tmp.unlink(missing_ok=True)

    def _create(self) -> None:
        if self.n_frames == 0:
            return
        for key, empty in frame_arrays(self._header).items():
            parent, _, leaf = key.rpartition("/")
            group = self._f[parent]
            attrs = dict(group[leaf].attrs)
            del group[leaf]
            trailing = empty.shape[1:]
            ds = group.create_dataset(
                leaf,
                shape=(0, *trailing),
                dtype=empty.dtype,
                chunks=(min(TRACKER_CHUNK_FRAMES, self.n_frames), *trailing),
                maxshape=(None, *trailing),
                compression="gzip",
                compression_opts=1,
                shuffle=True,
            )
            ds.attrs.update(attrs)

    def append(self, frames: Recording) -> None:
        """Append the frames of `frames` (a recording like the header, with frames)."""
        if self._f is None:
            raise RuntimeError("RecordingWriter.append outside its `with` block")
        arrays = frame_arrays(frames)
        if tuple(arrays) != self._keys:
            raise ValueError(f"frames hold {sorted(arrays)}, the header {sorted(self._keys)}")
        k = int(arrays["tracker/time"].shape[0])
        if k == 0:
            return
        if self.written + k > self.n_frames:
            raise ValueError(f"more than the {self.n_frames} frames announced")
        for key, a in arrays.items():
            want = (k, *self._f[key].shape[1:])
            if a.shape != want:
                raise ValueError(f"{self.path}: /{key} has shape {a.shape}, expected {want}")
        time = np.asarray(frames.time, np.float64)
        steps = np.diff(time if self._last_time is None else np.r_[self._last_time, time])
        if not (np.all(np.isfinite(time)) and np.all(steps > 0)):
            raise ValueError(f"{self.path}: /tracker/time must be finite, strictly increasing")
        self._last_time = float(time[-1])
        c = min(TRACKER_CHUNK_FRAMES, self.n_frames)
        for key in self._keys:
            dtype = self._f[key].dtype
            a = np.asarray(arrays[key]).astype(dtype, copy=False)
            tail = self._tail.get(key)
            if tail is not None and tail.shape[0]:
                a = np.concatenate([tail, a])
            whole = a.shape[0] - a.shape[0] % c
            self._write(key, a[:whole])
            self._tail[key] = a[whole:].copy()
        self.written += k

    def _write(self, key: str, a: np.ndarray) -> None:
        if a.shape[0] == 0:
            return
        ds = self._f[key]
        n0 = ds.shape[0]
        ds.resize(n0 + a.shape[0], axis=0)
        ds[n0:] = a

    def _flush_tail(self) -> None:
        for key, tail in self._tail.items():
            self._write(key, tail)
        self._tail = {}
