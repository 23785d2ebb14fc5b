"""Bundle calibration of a recording read block by block (`open_recording`): the same
estimate as from the recording in memory, for a length that is no multiple of the file's
or the fit's blocks, and an unreadable chunk is a one-line error that names its frames."""

import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from robtraj import open_recording, write_recording
from robtraj.estimate import _calib_frames
from robtraj.estimate.calibration import fit
from robtraj.recording import TRACKER_CHUNK_FRAMES
from robtraj.sim import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cli"))
from cli_helpers import assert_one_line_error, run_cli  # noqa: E402

RATE = 250.0
#: the file's chunk times a prime, and a ragged remainder (a prime too)
N = TRACKER_CHUNK_FRAMES * 7 + 13
#: frames per block of the fit read from the file: neither a divisor nor a multiple of N
#: or of the file's chunk (kernel chunks of 256 frames, 4 per block)
BLOCK = 1024


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rec = simulate("paper", seed=3, duration=N / RATE, rate=RATE)
    assert rec.positions.shape[0] == N
    path = tmp_path_factory.mktemp("chunked") / "rec.h5"
    write_recording(rec, path)
    return rec, path


def _agree(a, b, rtol=1e-10):
    """The parameters, their covariance and the fit's statistics agree to `rtol`."""
    for name in ("camera_from_base", "flange_from_tool"):
        pa, pb = getattr(a, name), getattr(b, name)
        np.testing.assert_allclose(pb.position, pa.position, rtol=rtol, atol=0)
        np.testing.assert_allclose(pb.quaternion_wxyz, pa.quaternion_wxyz, rtol=rtol, atol=0)
    np.testing.assert_allclose(b.constellation, a.constellation, rtol=rtol, atol=0)
    scale = np.max(np.abs(a.covariance))
    np.testing.assert_allclose(b.covariance / scale, a.covariance / scale, rtol=0, atol=rtol)
    for stat in ("chi2", "log_likelihood", "residual_rms_m"):
        np.testing.assert_allclose(getattr(b, stat), getattr(a, stat), rtol=rtol)
    np.testing.assert_allclose(b.residual_rms_per_frame, a.residual_rms_per_frame, rtol=rtol)
    np.testing.assert_array_equal(b.outlier_frames, a.outlier_frames)
    assert (a.iterations, a.converged) == (b.iterations, b.converged)


@pytest.mark.parametrize("robust", [None, "huber"])
def test_a_recording_read_block_by_block_calibrates_as_in_memory(recording, monkeypatch, robust):
    """In memory the recording is one block; from the file it is read in blocks of
    `BLOCK` frames across the file's chunks, the last one ragged."""
    rec, path = recording
    whole = fit(rec, robust=robust)
    monkeypatch.setattr(_calib_frames, "BLOCK_FRAMES", BLOCK)
    blocks = set()
    block = _calib_frames.TrackerFrames.block

    def counted(self, i, x=None):
        blocks.add(i)
        return block(self, i, x)

    monkeypatch.setattr(_calib_frames.TrackerFrames, "block", counted)
    with open_recording(path) as lazy:
        read = fit(lazy, robust=robust, per_observation=False)
    assert len(blocks) >= N // BLOCK  # the frames of the fit, a ragged last block
    _agree(whole, read)
    assert read.residuals is None and read.weights is None
    assert whole.residuals.shape == (N, whole.led_ids.size, 3)


def test_an_unreadable_chunk_is_one_line_naming_its_frames(recording, tmp_path, capsys):
    _, path = recording
    bad = tmp_path / "bad.h5"
    shutil.copy(path, bad)
    with h5py.File(bad, "r") as f:
        ds = f["tracker/positions"]
        c = ds.chunks[0]
        info = ds.id.get_chunk_info(4)  # in the middle of the recording
    first = info.chunk_offset[0]
    assert 0 < first and first + c < N
    with open(bad, "r+b") as fh:  # the chunk's compressed bytes overwritten
        fh.seek(info.byte_offset)
        fh.write(b"\x00" * info.size)
    out = tmp_path / "calib.json"
    code, _, err = run_cli(capsys, "calibrate", bad, "-o", out)
    assert_one_line_error(
        code, err, f"frames {first}–{first + c - 1} of /tracker/positions", "unreadable"
    )
    assert not out.exists()
