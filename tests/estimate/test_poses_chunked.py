"""Poses from a recording read chunk by chunk (`open_recording`): the same result as from
the recording in memory, for every weighting scheme, memory of a chunk, and an unreadable
chunk is a one-line error that names its frames."""

import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from robtraj import RecordingError, open_recording, read_recording, write_recording
from robtraj._recording_reader import LazyFrames
from robtraj.estimate import estimate_poses
from robtraj.sim import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cli"))
from cli_helpers import assert_one_line_error, run_cli  # noqa: E402

CHUNK = 512
N = CHUNK * 12 + 13  # several chunks and a ragged last one (13 frames, a prime)
SCHEMES = [
    "uniform",
    "inverse_variance",
    "pairwise_inverse_variance",
    "threshold",
    "led_noise",
    "robust",
    "emission_angle",
]
FIELDS = ["position", "quaternion_wxyz", "rms", "n_used", "valid", "constellation"]


def _first(rec, n):
    """The first `n` frames of a simulated recording (per-frame data and truth)."""
    truth = rec.truth
    pose = type(truth.tool_pose)(truth.tool_pose.position[:n], truth.tool_pose.quaternion_wxyz[:n])
    return rec.replace(
        time=rec.time[:n],
        frame_index=rec.frame_index[:n],
        positions=rec.positions[:n],
        status=None if rec.status is None else rec.status[:n],
        temperature=None if rec.temperature is None else rec.temperature[:n],
        program=None,
        truth=type(truth)(
            pose, truth.camera_from_base, truth.flange_from_tool, truth.constellation, truth.effects
        ),
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rec = _first(simulate("paper", seed=5, duration=26.0, rate=250.0), N)
    path = tmp_path_factory.mktemp("chunked") / "rec.h5"
    write_recording(rec, path)
    return read_recording(path), path


def _assert_same(got, want, rtol=1e-10):
    assert got.constellation_source == want.constellation_source
    for f in FIELDS:
        np.testing.assert_allclose(
            getattr(got, f), getattr(want, f), rtol=rtol, atol=0, equal_nan=True, err_msg=f
        )


@pytest.mark.parametrize("weighting", SCHEMES)
def test_lazy_and_in_memory_recordings_give_the_same_poses(recording, weighting):
    rec, path = recording
    want = estimate_poses(rec, weighting=weighting, chunk=CHUNK)
    assert want.constellation_source == "registered" and want.valid.mean() > 0.99
    with open_recording(path) as lazy:
        assert isinstance(lazy.positions, LazyFrames)
        got = estimate_poses(lazy, weighting=weighting, chunk=CHUNK)
    _assert_same(got, want)
    np.testing.assert_allclose(
        got.registration.uncertainty, want.registration.uncertainty, rtol=1e-10
    )


@pytest.mark.parametrize("weighting", ["led_noise", "robust", "emission_angle"])
def test_the_chunk_length_does_not_change_the_poses(recording, weighting):
    """Chunks only split the work: the LED variance's reference distances restart at a
    chunk's first frame (a rounding-level change), the recording-level statistics (noise
    model, median residual) are exact."""
    rec, _ = recording
    _assert_same(
        estimate_poses(rec, weighting=weighting, chunk=CHUNK),
        estimate_poses(rec, weighting=weighting),
        rtol=1e-8,
    )


def test_a_lazy_pass_reads_one_chunk_at_a_time(recording, monkeypatch):
    _, path = recording
    sizes = []
    read = LazyFrames.read

    def spy(self, a, b):
        sizes.append(b - a)
        return read(self, a, b)

    monkeypatch.setattr(LazyFrames, "read", spy)
    with open_recording(path) as lazy:
        est = estimate_poses(lazy, weighting="robust", chunk=CHUNK)
    assert est.valid.all()
    # a chunk plus its halo: half a window (0.1 s), the static test's lag (0.2 s)
    assert 0 < max(sizes) <= CHUNK + 64, max(sizes)
    assert sum(sizes) >= 4 * N  # every pass reads the frames again


def test_open_recording_reads_what_read_recording_reads(recording):
    rec, path = recording
    with open_recording(path) as lazy:
        np.testing.assert_array_equal(np.asarray(lazy.positions), rec.positions)
        np.testing.assert_array_equal(lazy.positions[100:300, 2], rec.positions[100:300, 2])
        np.testing.assert_array_equal(lazy.status[N - 5 :], rec.status[N - 5 :])
        np.testing.assert_array_equal(lazy.time, rec.time)
        assert lazy.positions.shape == rec.positions.shape and lazy.n_frames == N
        assert lazy.truth is not None and lazy.tool is not None
    # commands that never compare with the truth leave it in the file, not as extras
    with open_recording(path, truth=False) as lazy:
        assert lazy.truth is None and lazy.extras == {} and lazy.extra_attrs == {}
        np.testing.assert_array_equal(lazy.time, rec.time)
        assert lazy.tool is not None and lazy.robot is not None


def _plain_file(path, n_time=5, n_positions=5, **attrs):
    """A device recording written with plain h5py, /tracker/positions of `n_positions`
    frames (a recorder killed mid-flush leaves it longer than /tracker/time)."""
    with h5py.File(path, "w") as f:
        f.attrs.update({"schema": "robtraj.recording", "schema_version": 1, "source": "device"})
        f.attrs.update(attrs)
        f["tracker/time"] = np.arange(n_time) * 1e-3
        f["tracker/frame_index"] = np.arange(n_time, dtype=np.uint64)
        f["tracker/led_ids"] = np.arange(3, dtype=np.int32)
        f["tracker/positions"] = np.random.default_rng(0).normal(size=(n_positions, 3, 3))
    return path


def test_open_recording_trims_and_rejects_as_read_recording_does(tmp_path):
    path = _plain_file(tmp_path / "cut.h5", n_time=5, n_positions=7)
    with open_recording(path) as lazy:
        np.testing.assert_array_equal(np.asarray(lazy.positions), read_recording(path).positions)
        assert lazy.positions.shape == (5, 3, 3)
    bad = _plain_file(tmp_path / "new.h5", schema_version=2)
    with pytest.raises(RecordingError, match="newer"), open_recording(bad):
        pass
    short = _plain_file(tmp_path / "short.h5", n_time=5, n_positions=4, source="simulation")
    with pytest.raises(RecordingError, match="/tracker/positions has shape"):
        with open_recording(short):
            pass


def test_an_unreadable_chunk_is_one_line_naming_its_frames(recording, tmp_path, capsys):
    _, path = recording
    bad = tmp_path / "bad.h5"
    shutil.copy(path, bad)
    with h5py.File(bad, "r") as f:
        ds = f["tracker/positions"]
        c = ds.chunks[0]
        info = ds.id.get_chunk_info(3)  # in the middle of the recording
    first = info.chunk_offset[0]
    assert 0 < first and first + c < N
    with open(bad, "r+b") as fh:  # the chunk's compressed bytes overwritten
        fh.seek(info.byte_offset)
        fh.write(b"\x00" * info.size)
    out = tmp_path / "poses.h5"
    code, _, err = run_cli(capsys, "poses", bad, "-o", out)
    assert_one_line_error(
        code, err, f"frames {first}–{first + c - 1} of /tracker/positions", "unreadable"
    )
    assert not out.exists()
