"""Simulating straight to a file (`simulate_to`): the file is the in-memory recording's,
the chunk size changes nothing, and an interrupted write leaves nothing behind."""

import h5py
import numpy as np
import pytest

import robtraj.sim._generate as simulator
from robtraj import UserError, read_recording, write_recording
from robtraj.recording import Pose
from robtraj.sim import (
    PeriodicJointError,
    SightLineBias,
    VelocityDeadbandError,
    simulate,
    simulate_to,
)

UNMODELLED = (PeriodicJointError(2, 3, 1e-4), SightLineBias(50e-6), VelocityDeadbandError(3, 1e-4))
EFFECTS = {
    "time_offset": 0.004,
    "backlash": [0, 1e-4, 1e-4, 0, 0, 0],
    "thermal_drift": [1e-5, 0, -1e-5],
}


def _commanded() -> Pose:
    targets = simulate("calibration", seed=4, duration=12.0, rate=10.0).program.targets
    return Pose(targets.position + np.array([1e-4, -2e-4, 5e-5]), targets.quaternion_wxyz)


CASES = {
    "paper": dict(scenario="paper", seed=0, duration=4.0, rate=500.0),
    "crossing, no truth": dict(scenario="crossing", seed=7, duration=2.0, rate=200.0, truth=False),
    "calibration, effects, commanded": dict(
        scenario="calibration", seed=4, duration=12.0, rate=50.0, effects=EFFECTS, commanded=None
    ),
    "workspace, unmodelled": dict(
        scenario="workspace", seed=1, duration=24.0, rate=25.0, unmodelled=UNMODELLED
    ),
}


def _options(case: str) -> tuple[str, dict]:
    options = dict(CASES[case])
    if "commanded" in options:
        options["commanded"] = _commanded()
    return options.pop("scenario"), options


def _datasets(path) -> dict:
    """Every dataset's values and storage (chunks, filters, extent), every attribute
    (the root's but `created`)."""
    out = {}
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            attrs = {k: v for k, v in obj.attrs.items() if k != "created"}
            if isinstance(obj, h5py.Dataset):
                storage = (obj.dtype, obj.chunks, obj.maxshape, obj.compression, obj.shuffle)
                out[name] = (obj[()], storage, attrs)
            else:
                out[name] = attrs

        f.visititems(visit)
        out["/"] = {k: v for k, v in f.attrs.items() if k != "created"}
    return out


def _assert_same_file(a, b) -> None:
    da, db = _datasets(a), _datasets(b)
    assert sorted(da) == sorted(db)
    for name, value in da.items():
        if isinstance(value, dict):
            assert str(value) == str(db[name]), name
            continue
        (data, storage, attrs), (data_b, storage_b, attrs_b) = value, db[name]
        assert storage == storage_b, name
        assert str(attrs) == str(attrs_b), name
        np.testing.assert_array_equal(data, data_b, err_msg=name)


def _assert_same_recording(a, b) -> None:
    for name in ["time", "frame_index", "led_ids", "positions", "status", "temperature"]:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.program.segment, b.program.segment)
    np.testing.assert_array_equal(a.robot.joints, b.robot.joints)
    assert (a.truth is None) == (b.truth is None)
    if a.truth is not None:
        np.testing.assert_array_equal(a.truth.tool_pose.position, b.truth.tool_pose.position)
        np.testing.assert_array_equal(
            a.truth.tool_pose.quaternion_wxyz, b.truth.tool_pose.quaternion_wxyz
        )
        assert a.truth.effects == b.truth.effects
    assert {k: v for k, v in a.attrs.items() if k != "created"} == {
        k: v for k, v in b.attrs.items() if k != "created"
    }


@pytest.mark.parametrize("chunk", [None, 257])
@pytest.mark.parametrize("case", list(CASES))
def test_streamed_file_is_the_written_in_memory_recording(tmp_path, monkeypatch, case, chunk):
    """`simulate_to` writes what `write_recording(simulate(...))` writes: values, storage
    and attributes (but `created`); chunks of 257 frames are not HDF5's 1000."""
    if chunk is not None:
        monkeypatch.setattr(simulator, "CHUNK_FRAMES", chunk)
    scenario, options = _options(case)
    rec = simulate(scenario, **options)
    done = simulate_to(tmp_path / "streamed.h5", scenario, **options)
    write_recording(rec, tmp_path / "written.h5")
    _assert_same_file(tmp_path / "streamed.h5", tmp_path / "written.h5")
    _assert_same_recording(
        read_recording(tmp_path / "streamed.h5"), read_recording(tmp_path / "written.h5")
    )

    seen = rec.visible.sum(1)
    assert (done.n_frames, done.n_leds, done.seen_min) == (rec.n_frames, rec.n_leds, seen.min())
    assert done.seen_mean == pytest.approx(seen.mean(), rel=1e-12)
    assert done.time_span == pytest.approx(rec.time[-1] - rec.time[0], rel=1e-12)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["streamed.h5", "written.h5"]


@pytest.mark.parametrize("chunk", [61, 257])
def test_the_chunk_size_changes_nothing(monkeypatch, chunk):
    """2000 frames in chunks of a prime size (7 whole chunks and a part for 257) equal
    the recording made in one chunk. The random draws (temperature noise, drop-outs, LED
    noise), hence everything derived from them, are exactly the same; XLA may round the
    forward model differently for another chunk shape (it does for chunks under 256
    frames on CPU), so the LED and tool positions are equal to rounding."""
    options = dict(seed=3, duration=10.0, rate=200.0, effects=EFFECTS, unmodelled=UNMODELLED)
    whole = simulate("crossing", **options)
    monkeypatch.setattr(simulator, "CHUNK_FRAMES", chunk)
    chunked = simulate("crossing", **options)
    assert whole.n_frames == 2000
    for name in ["time", "frame_index", "status", "temperature"]:
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)
    np.testing.assert_array_equal(chunked.program.segment, whole.program.segment)
    np.testing.assert_array_equal(chunked.visible, whole.visible)
    np.testing.assert_array_equal(chunked.robot.joints, whole.robot.joints)
    np.testing.assert_allclose(chunked.positions, whole.positions, rtol=0, atol=1e-12)
    for name in ["position", "quaternion_wxyz"]:
        np.testing.assert_allclose(
            getattr(chunked.truth.tool_pose, name),
            getattr(whole.truth.tool_pose, name),
            rtol=0,
            atol=1e-12,
        )


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
@pytest.mark.parametrize("existing", [False, True])
def test_an_interrupted_write_leaves_no_file(tmp_path, monkeypatch, error, existing):
    """A failure or Ctrl-C in the third chunk leaves nothing under the final name (and
    no temporary file); a file that was there (``overwrite=True``) is untouched."""
    monkeypatch.setattr(simulator, "CHUNK_FRAMES", 100)
    observe, calls = simulator._observe, []

    def failing(*args):
        calls.append(1)
        if len(calls) == 3:
            raise error("interrupted")
        return observe(*args)

    monkeypatch.setattr(simulator, "_observe", failing)
    out = tmp_path / "rec.h5"
    if existing:
        out.write_text("earlier recording")
    with pytest.raises(error, match="interrupted"):
        simulate_to(out, "paper", duration=2.0, rate=250.0, overwrite=existing)
    assert len(calls) == 3
    if existing:
        assert out.read_text() == "earlier recording"
        assert list(tmp_path.iterdir()) == [out]
    else:
        assert list(tmp_path.iterdir()) == []


def test_an_existing_file_is_refused_before_any_work(tmp_path, monkeypatch):
    def forbidden(*args):
        raise AssertionError("simulated before refusing the output")

    monkeypatch.setattr(simulator, "joint_log", forbidden)
    monkeypatch.setattr(simulator, "_observe", forbidden)
    out = tmp_path / "rec.h5"
    out.write_text("earlier recording")
    with pytest.raises(UserError, match="exists"):
        simulate_to(out, "paper", duration=1.0, rate=50.0)
    assert out.read_text() == "earlier recording"
    assert list(tmp_path.iterdir()) == [out]


def test_the_command_streams_the_recording(tmp_path, capsys):
    """`robtraj simulate` writes `simulate`'s recording and sums it up from the chunks."""
    from robtraj.cli import main

    out = tmp_path / "rec.h5"
    args = ["--scenario", "paper", "--duration", "3", "--rate", "200", "--seed", "2"]
    assert main(["simulate", str(out), *args, "--effect", "time_offset=0.003"]) == 0
    rec = simulate("paper", seed=2, duration=3.0, rate=200.0, effects={"time_offset": 0.003})
    _assert_same_file(out, write_recording(rec, tmp_path / "written.h5"))
    seen = rec.visible.sum(1)
    line = capsys.readouterr().out
    assert f"600 frames at 200 Hz (3.0 s), 18 LEDs, {seen.mean():.1f} seen per frame" in line
    assert f"(min {seen.min()}), effects: time_offset=0.003" in line
