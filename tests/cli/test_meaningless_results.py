"""Results without meaning are refused or warned about, on a short simulated ISO cube run:
a calibration of another setup is refused; NaN characteristics are warned about (exit 1)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli, true_calibration

from robtraj.cli import _analysis_inputs
from robtraj.recording import write_recording
from robtraj.sim import simulate

SHIFT = np.array([0.05, 0.0, 0.0])  # [m] the camera moved by 50 mm


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    # 8 s at 25 Hz: too short for a complete cycle of every ISO path (NaN characteristics)
    rec = simulate("iso_cube", seed=3, duration=8.0, rate=25.0)
    write_recording(rec, d / "iso.h5")
    tr = rec.truth
    doc = true_calibration(rec)
    (d / "same.json").write_text(json.dumps(doc))
    moved = copy.deepcopy(doc)
    moved["camera_from_base"]["position"] = (tr.camera_from_base.position + SHIFT).tolist()
    (d / "moved.json").write_text(json.dumps(moved))
    return d, rec


def test_calibration_of_another_setup_is_refused(setup, capsys, tmp_path):
    d, rec = setup
    for command in ("iso9283",):  # deviation reads its inputs through the same `load`
        code, _, err = run_cli(
            capsys, command, d / "iso.h5", "--calibration", d / "moved.json",
            "--json", tmp_path / f"{command}.json",
        )  # fmt: skip
        line = assert_one_line_error(code, err, "another setup", "robtraj calibrate")
        assert not (tmp_path / f"{command}.json").exists()
    # the distance it quotes is the camera shift: the measured camera-frame poses do not
    # depend on camera←base, the predicted ones move with it rigidly
    quoted = float(line.split("are ")[1].split(" mm")[0]) * 1e-3
    assert abs(quoted - np.linalg.norm(SHIFT)) < 1e-3, line


def test_same_setup_passes_and_nan_characteristics_are_warned(setup, capsys, tmp_path):
    d, rec = setup
    out = tmp_path / "iso.json"
    code, stdout, err = run_cli(
        capsys, "iso9283", d / "iso.h5", "--calibration", d / "same.json", "--json", out
    )
    doc = json.loads(out.read_text())
    warnings = [line for line in err.splitlines() if line.startswith("robtraj: warning: ")]
    undefined = [f"path {name}" for name, p in doc["paths"].items() if p["AT_mm"] is None] + [
        f"pose {name}" for name, p in doc["poses"].items() if p["AP_mm"] is None
    ]
    assert undefined, "the 8 s run was meant to leave some characteristic undefined"
    assert code == 1, err
    for u in undefined:
        assert any(w.startswith(f"robtraj: warning: {u}:") for w in warnings), (u, err)
    assert "Traceback" not in err


@pytest.mark.exhaustive
def test_setup_discrepancy_of_the_true_calibration_is_at_noise_level(setup):
    d, rec = setup
    from robtraj.calibration_file import load_calibration
    from robtraj.estimate._base_frame import base_frame_poses

    calib = load_calibration(d / "same.json")
    bf = base_frame_poses(rec, calib)
    got = _analysis_inputs.setup_discrepancy(rec, calib, bf)
    # per-frame pose error of an 18-LED fit with 15-75 µm LED noise: well under 0.2 mm
    assert got < 2e-4, got
    moved = load_calibration(d / "moved.json")
    shifted = _analysis_inputs.setup_discrepancy(rec, moved, bf)
    assert abs(shifted - np.linalg.norm(SHIFT)) < 2e-4 + got


def test_a_constant_orientation_run_names_what_it_cannot_determine_and_iso9283_warns(
    setup, capsys, tmp_path
):
    """`calibrate` on a run that never turns the tool (the `crossing` scenario) starts
    from a point registration, names camera←base against flange←tool translation as
    undetermined (σ not determined), and `iso9283` with it warns, naming them and the fix;
    the JSON lists them. The determined parts are right: the rotations within 1 mrad."""
    d, rec_iso = setup
    rec = simulate("crossing", seed=3, duration=10.0, rate=25.0)  # the same setup as `iso.h5`
    write_recording(rec, tmp_path / "cross.h5")
    code, out_text, err = run_cli(
        capsys, "calibrate", tmp_path / "cross.h5", "-o", tmp_path / "weak.json"
    )
    assert code == 0, err
    assert "not determined" in out_text
    assert "measure next" in out_text  # the poses that would determine them
    doc = json.loads((tmp_path / "weak.json").read_text())
    names = [f"{t}.t{c}" for t in ("camera_from_base", "flange_from_tool") for c in "xyz"]
    assert sorted(doc["identifiability"]["undetermined"]) == sorted(names)
    got = np.asarray(doc["camera_from_base"]["quaternion_wxyz"])
    want = rec.truth.camera_from_base.quaternion_wxyz
    assert 2 * np.arccos(min(1.0, abs(float(got @ want)))) < 1e-3
    out = tmp_path / "iso.json"
    code, _, err = run_cli(
        capsys, "iso9283", d / "iso.h5", "--calibration", tmp_path / "weak.json", "--json", out
    )
    warning = [line for line in err.splitlines() if "does not determine" in line]
    assert len(warning) == 1 and "flange_from_tool.tx" in warning[0]
    assert "reorientations about two axes" in warning[0]
    assert sorted(json.loads(out.read_text())["calibration_undetermined"]) == sorted(names)
    # the calibration of this setup without the defect: no such warning
    code, _, err = run_cli(
        capsys, "iso9283", d / "iso.h5", "--calibration", d / "same.json",
        "--json", tmp_path / "iso2.json",
    )  # fmt: skip
    assert "does not determine" not in err
    assert json.loads((tmp_path / "iso2.json").read_text())["calibration_undetermined"] == []
