"""The recording appender's own chunk compression gives an ordinary shuffle+gzip dataset."""

from __future__ import annotations

import zlib

import h5py
import numpy as np
import pytest

from robtraj import recording
from robtraj.recording import RecordingAppender, read_recording

M = 5
# batch sizes crossing the 1000-frame chunk boundary in every way: empty, single frames,
# a chunk filled from its middle, whole chunks, more than one chunk at once
BATCHES = [1, 0, 998, 1, 1, 1500, 276, 1000, 1224, 3]


def _frames(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    pos = np.float32(rng.normal(size=(n, M, 3)) * 300.0 + 2000.0).astype(np.float64) / 1000.0
    status = rng.integers(0, 4, size=(n, M)).astype(np.uint8)
    pos[status == 1] = np.nan
    return np.arange(n) / 1000.0, np.arange(n, dtype=np.uint64), pos, status


@pytest.mark.parametrize("deflate", ["isal", "zlib"])
def test_appended_chunks_read_back_bit_identical_by_plain_h5py(tmp_path, monkeypatch, deflate):
    """Chunks deflated by ISA-L (plane by plane) or, without the isal package, by zlib."""
    if deflate == "isal":
        assert recording._isal_zlib is not None, "isal is a dependency: pip install isal"
    else:
        monkeypatch.setattr(recording, "_isal_zlib", None)
    n = sum(BATCHES)
    t, idx, pos, status = _frames(n)
    path = tmp_path / "a.h5"
    app = RecordingAppender(path, np.arange(M))
    i = 0
    for k in BATCHES:
        app.append(t[i : i + k], idx[i : i + k], pos[i : i + k], status[i : i + k])
        app.flush()
        i += k
        # what a crash would leave: the file read by another process after this flush
        with h5py.File(path, "r", libver="latest", swmr=True) as f:
            got = f["tracker/positions"][()]
        assert got.tobytes() == pos[:i].tobytes()
    app.close()

    # reference: the same arrays through h5py's own shuffle+gzip filter pipeline
    ref = tmp_path / "ref.h5"
    with h5py.File(ref, "w") as f:
        f.create_dataset("p", data=pos, chunks=(1000, M, 3), compression="gzip", shuffle=True)
        f.create_dataset("s", data=status, chunks=(1000, M), compression="gzip", shuffle=True)
    with h5py.File(path, "r") as f, h5py.File(ref, "r") as g:
        p, s = f["tracker/positions"], f["tracker/status"]
        assert (p.compression, p.shuffle, s.compression) == ("gzip", True, "gzip")
        assert p[()].tobytes() == g["p"][()].tobytes() == pos.tobytes()
        np.testing.assert_array_equal(s[()], g["s"][()])
        # a stored chunk inflated and unshuffled by hand is the frames, byte for byte
        mask, blob = p.id.read_direct_chunk((1000, 0, 0))
        assert mask == 0
        planes = np.frombuffer(zlib.decompress(blob), np.uint8).reshape(8, -1)
        np.testing.assert_array_equal(
            planes.T.copy().view(np.float64).ravel(), pos[1000:2000].ravel()
        )
    rec = read_recording(path)
    assert rec.positions.tobytes() == pos.tobytes()
    np.testing.assert_array_equal(rec.status, status)
    np.testing.assert_array_equal(rec.frame_index, idx)
