"""A long recording's discrepancy search runs on evenly spaced frames read block by block
from the file, and the named model is fitted again on every frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robtraj._recording_reader import open_recording
from robtraj.analysis import _search_frames
from robtraj.analysis._search_frames import search_recording, search_step
from robtraj.calibration_file import load_calibration
from robtraj.cli import main
from robtraj.estimate.calibration import fit
from robtraj.recording import read_recording

#: the frames of the recording below, and the most a search may take: one in 3
N_FRAMES, MAX_FRAMES = 2000, 700


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 40 s calibration run at 50 Hz, joint 3 off by 0.4 mrad."""
    path = tmp_path_factory.mktemp("long") / "rec.h5"
    args = ["simulate", path, "--scenario", "calibration", "--seed", 2, "--duration", 40,
            "--rate", 50, "--effect", "joint_offset=0,0,4e-4,0,0,0"]  # fmt: skip
    assert main([str(a) for a in args]) == 0
    return path


def test_the_subset_is_every_kth_frame_read_block_by_block(recording, monkeypatch):
    """Against the recording read whole and sliced ``[::k]``: every per-frame dataset, with
    blocks (7 frames, a multiple of k only by rounding up) that leave a ragged last one;
    the robot log and the program's targets whole."""
    whole = read_recording(recording)
    assert whole.n_frames == N_FRAMES
    monkeypatch.setattr(_search_frames, "_READ", 7)
    k = search_step(N_FRAMES, MAX_FRAMES)
    assert k == 3 and search_step(N_FRAMES, N_FRAMES) == 1
    with open_recording(recording, truth=False) as lazy:
        sub, every = search_recording(lazy, MAX_FRAMES)
        same, one = search_recording(lazy, N_FRAMES)
    assert every == k and one == 1
    for field in ("time", "frame_index", "positions", "temperature"):
        if getattr(whole, field) is None:
            assert getattr(sub, field) is None
            continue
        np.testing.assert_array_equal(getattr(sub, field), getattr(whole, field)[::k])
        np.testing.assert_array_equal(getattr(same, field), getattr(whole, field))
    assert sub.status is None or np.array_equal(sub.status, np.asarray(whole.status)[::k])
    np.testing.assert_array_equal(sub.program.segment, whole.program.segment[::k])
    np.testing.assert_array_equal(sub.robot.joints, whole.robot.joints)
    np.testing.assert_array_equal(sub.program.targets.position, whole.program.targets.position)
    assert sub.truth is None and isinstance(sub.positions, np.ndarray)


def test_a_long_recording_is_searched_on_a_subset_and_fitted_on_all_frames(
    recording, monkeypatch, capsys, tmp_path
):
    """`robtraj discrepancy` on a recording above the search's frames: the search names
    the hidden joint offset on one frame in 3 (said on stdout and in the JSON), and the
    written model is the named model fitted on all frames: the same residual count and,
    from its own start, the same estimate as a direct fit of the whole recording."""
    monkeypatch.setattr(_search_frames, "SEARCH_FRAMES", MAX_FRAMES)
    out, named = tmp_path / "d.json", tmp_path / "named.json"
    argv = ["discrepancy", recording, "--json", out, "--calibration-out", named]
    assert main([str(a) for a in argv]) == 0
    text = capsys.readouterr().out
    assert f"searched on one frame in 3 (667 of {N_FRAMES}" in text, text
    doc = json.loads(out.read_text())
    assert doc["search_frames"] == {"every": 3, "frames": 667, "of": N_FRAMES}
    assert doc["named"] == ["joint_offset"], doc["named"]
    calib = load_calibration(named)
    direct = fit(read_recording(recording), estimate=calib.estimated, per_observation=False)
    assert calib.n_residuals == direct.n_residuals
    sigma = direct.sigma["joint_offset[2]"]
    assert abs(calib.effects["joint_offset"][2] - direct.effects["joint_offset"][2]) < 1e-3 * sigma
    # the search's own fit saw a third of the observations
    step = doc["steps"][0]["parameters"]["joint_offset[2]"]
    assert step["sigma"] > 1.4 * sigma
