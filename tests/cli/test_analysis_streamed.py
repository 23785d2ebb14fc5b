"""`deviation` and `iso9283` read the LED positions by frame ranges (`open_recording`):
their base-frame poses equal those of the recording read whole, with and without a
calibrated tracker scale (divided out as the frames are read)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from cli_helpers import true_calibration

from robtraj.calibration_file import load_calibration
from robtraj.cli import _analysis_inputs, main
from robtraj.cli._deviation import deviation_of
from robtraj.estimate import base_frame_poses
from robtraj.recording import read_recording, write_recording
from robtraj.sim import simulate


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    d = tmp_path_factory.mktemp("streamed")
    rec = simulate("iso_cube", seed=5, duration=12.0, rate=25.0)
    write_recording(rec, d / "iso.h5")
    doc = true_calibration(rec)
    (d / "plain.json").write_text(json.dumps(doc))
    (d / "scaled.json").write_text(json.dumps({**doc, "effects": {"tracker_scale": 2e-4}}))
    return d


@pytest.mark.parametrize("calibration", ["plain.json", "scaled.json"])
def test_poses_read_by_frame_ranges_equal_those_of_the_whole_recording(recorded, calibration):
    path, calib_path = recorded / "iso.h5", recorded / calibration
    args = argparse.Namespace(
        recording=str(path), calibration=str(calib_path), weighting="led_noise"
    )
    rec, calib, streamed = _analysis_inputs.load(args)
    whole = read_recording(path)
    direct = base_frame_poses(whole, load_calibration(calib_path))
    assert streamed.valid.sum() > 0.9 * streamed.valid.size
    np.testing.assert_array_equal(streamed.valid, direct.valid)
    for a, b in (
        (streamed.position, direct.position),
        (streamed.quaternion_wxyz, direct.quaternion_wxyz),
    ):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13, equal_nan=True)
    d1, d2 = deviation_of(rec, streamed)[1].summary(), deviation_of(whole, direct)[1].summary()
    assert d1.distance_rms == pytest.approx(d2.distance_rms, rel=1e-10)


def test_the_commands_run_on_a_recording_opened_by_frame_ranges(recorded, tmp_path):
    """`deviation` and `iso9283` end to end on the lazily opened recording: the LED
    positions are not read after the poses (they would fail on the closed file)."""
    # 12 s hold too few cycles of the ISO paths: iso9283 warns of the undefined ones (1)
    for command, code in (("deviation", 0), ("iso9283", 1)):
        out = tmp_path / f"{command}.json"
        args = [command, str(recorded / "iso.h5"), "--calibration", str(recorded / "plain.json")]
        assert main([*args, "--json", str(out), "--quiet"]) == code
        assert json.loads(out.read_text())
