"""`deviation`, `iso9283` and `report` read the LED positions by frame ranges
(`open_recording`): their base-frame poses equal those of the recording read whole, with
and without a calibrated tracker scale (divided out as the frames are read); the
report's LED visibility, variance and noise model equal those of the whole recording."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from cli_helpers import true_calibration

from robtraj import open_recording
from robtraj.calibration_file import load_calibration
from robtraj.cli import _analysis_inputs, main
from robtraj.cli._deviation import deviation_of
from robtraj.estimate import (
    base_frame_poses,
    chunked_led_variance,
    observation_noise,
    observation_noise_source,
    visible_frames,
)
from robtraj.recording import read_recording, write_recording
from robtraj.report._figures import IMAGE_COLUMNS, _binned, envelope, most_changing
from robtraj.report._path_sections import _speed
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


def test_report_runs_on_a_recording_opened_by_frame_ranges(recorded, tmp_path):
    """`report` end to end on the lazily opened recording, with the same deviation as
    the `deviation` command."""
    calib = str(recorded / "plain.json")
    out, dev = tmp_path / "report.json", tmp_path / "deviation.json"
    rec = str(recorded / "iso.h5")
    assert main(["report", rec, "--calibration", calib, "--out", str(tmp_path / "r"),
                 "--json", str(out), "--quiet"]) == 0  # fmt: skip
    assert main(["deviation", rec, "--calibration", calib, "--json", str(dev), "--quiet"]) == 0
    report = json.loads(out.read_text())
    assert (tmp_path / "r" / "leds.png").stat().st_size > 10_000
    assert (tmp_path / "r" / "noise_model.png").exists()
    assert report["deviation"] == json.loads(dev.read_text())["summary"]


def test_led_sections_read_by_frame_ranges_equal_the_whole_recording(recorded):
    """Visibility, the variance of the LEDs the figure shows and the noise model, each
    read in chunks that do not divide the recording (a ragged last chunk), against the
    recording read whole."""
    whole = read_recording(recorded / "iso.h5")
    with open_recording(recorded / "iso.h5") as rec:
        n = rec.n_frames
        chunk = 97  # prime, and not a divisor of n
        assert n % chunk
        visible = visible_frames(rec.positions, chunk)
        np.testing.assert_array_equal(visible, whole.visible)
        pick = most_changing(visible)
        part = chunked_led_variance(rec.positions, 21, "paper", chunk, keep=pick)
        model, _ = observation_noise_source(rec)
    full = chunked_led_variance(whole.positions, 21, "paper")
    np.testing.assert_allclose(part, full[:, pick], rtol=1e-10, equal_nan=True)
    direct, _ = observation_noise(whole)
    np.testing.assert_allclose(model.variance, direct.variance, rtol=1e-10)
    # the figure's LEDs: most visibility changes, as counted directly
    changes = np.abs(np.diff(whole.visible.astype(int), axis=0)).sum(0)
    assert set(changes[pick]) == set(np.sort(changes)[-3:])


def test_long_visibility_is_shown_as_the_fraction_seen_per_time_bin():
    rng = np.random.default_rng(0)
    n = 40 * IMAGE_COLUMNS + 7  # bins of 40 frames: counted in two groups of bins
    visible = rng.random((n, 5)) < 0.7
    binned = _binned(visible)
    assert binned.shape == (IMAGE_COLUMNS, 5)
    edges = np.linspace(0, n, IMAGE_COLUMNS + 1).astype(int)
    direct = np.array([visible[a:b].mean(0) for a, b in zip(edges[:-1], edges[1:])])
    np.testing.assert_allclose(binned, direct, rtol=1e-15)
    short = visible[:IMAGE_COLUMNS]
    np.testing.assert_array_equal(_binned(short), short.astype(float))


@pytest.mark.parametrize("runs, per_run", [(50, 7), (40, 3001)])
def test_figure_envelope_keeps_every_runs_extremes(runs, per_run):
    """Long per-frame curves are drawn by each run's extremes: compared with a direct
    per-run min/max (NaN ignored, ties: the first frame), every extreme is kept and nothing
    else; short series are drawn whole. Runs longer than `IMAGE_CHUNK` / 40 frames are
    taken in several groups."""
    rng = np.random.default_rng(3)
    n = per_run * runs + 13
    v = np.round(rng.normal(size=n), 1)  # ties within runs
    v[rng.random(n) < 0.1] = np.nan
    v[40:60] = np.nan  # a run without a finite value
    kept = envelope(v, runs)
    starts = np.linspace(0, n, runs + 1).astype(int)
    expected = set()
    for a, b in zip(starts[:-1], starts[1:]):
        run = v[a:b]
        if np.isfinite(run).any():
            expected |= {a + int(np.nanargmin(run)), a + int(np.nanargmax(run))}
    assert set(kept.tolist()) == expected
    assert np.all(np.diff(kept) > 0)
    np.testing.assert_array_equal(envelope(v[: 2 * runs], runs), np.arange(2 * runs))


@pytest.mark.parametrize("n", [2, 3, 101])
def test_speed_by_blocks_is_np_gradient(n):
    """The report's TCP speed, block by block with one frame either side, equals
    `np.gradient` over the whole series (uneven time steps, ragged last block)."""
    rng = np.random.default_rng(n)
    t = np.cumsum(rng.uniform(0.5, 1.5, n))
    p = rng.normal(size=(n, 3))
    want = np.linalg.norm(np.gradient(p, t, axis=0), axis=1)
    for block in (1, 2, 7, 64):
        np.testing.assert_array_equal(_speed(t, p, block), want)
