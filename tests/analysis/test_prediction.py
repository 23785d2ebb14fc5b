"""`robtraj evaluate` / `robtraj.analysis.predict`: a calibration predicting another
recording of the same robot and tool, on noise-free simulations with known truth."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from robtraj import write_recording
from robtraj.analysis import predict
from robtraj.estimate.calibration import fit
from robtraj.model import CameraModel
from robtraj.sim import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cli"))
from cli_helpers import assert_one_line_error, run_cli  # noqa: E402

#: hidden in both recordings: about 0.1 mm at the tool
EFFECT = {"joint_offset": [0.0, 3e-4, -2e-4, 0.0, 0.0, 0.0]}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Two noise-free campaigns of one setup (same seed: camera, tool, constellation),
    different programs; calibrated on the first with and without the hidden effect."""
    cam = CameraModel(sigma0=0.0)
    a = simulate("calibration", seed=4, duration=12.0, rate=50.0, effects=EFFECT, camera=cam)
    b = simulate("calibration", seed=4, duration=18.0, rate=50.0, effects=EFFECT, camera=cam)
    right, nominal = fit(a, estimate=("joint_offset",)), fit(a)
    d = tmp_path_factory.mktemp("prediction")
    write_recording(b, d / "b.h5")
    for name, c in (("right", right), ("nominal", nominal)):
        (d / f"{name}.json").write_text(json.dumps(c.to_json()))
    return {"b": b, "right": right, "nominal": nominal, "dir": d}


def test_the_right_model_predicts_the_other_recording_exactly(setup):
    """Noise-free: with the hidden effect calibrated, the predicted tool poses equal the
    measured ones to rounding; refitting the tool mount as well changes nothing."""
    right = setup["right"]
    assert right.unseen_leds, "the test needs LEDs the first recording never saw"
    for refit in (("camera_from_base",), ("camera_from_base", "flange_from_tool")):
        p = predict(setup["b"], right, refit)
        assert p.calibration.converged and p.measured_by == "leds"
        assert p.summary()["poses"] > 0.9 * setup["b"].time.size
        assert np.nanmax(p.position_error) < 1e-8 and np.nanmax(p.angle_error) < 1e-8
        assert p.summary()["gap_mm"] is None  # the simulation reports no tracker noise


def test_a_missing_effect_shows_as_prediction_error(setup):
    """The nominal model leaves the joint offsets out: tens of micrometres of error that the
    refitted camera←base cannot absorb."""
    p = predict(setup["b"], setup["nominal"])
    s = p.summary()
    assert 10e-3 < s["pos_rms_mm"] < 0.3 and s["ang_max_deg"] > 1e-3, s


def test_cli_writes_json_and_figure(setup, tmp_path, capsys):
    d = setup["dir"]
    out, png = tmp_path / "ev.json", tmp_path / "ev.png"
    args = ["evaluate", d / "b.h5", "--calibration", d / "nominal.json", "--json", out]
    code, stdout, _ = run_cli(capsys, *args, "--plot", png, "--refit", "camera,tool")
    assert code == 0 and "position error mean" in stdout
    doc = json.loads(out.read_text())
    errs = np.array(doc["per_pose"]["position_error_m"], float)
    assert doc["refit"] == ["camera_from_base", "flange_from_tool"]
    assert doc["summary"]["poses"] == np.isfinite(errs).sum()
    assert abs(doc["summary"]["pos_rms_mm"] - 1e3 * np.sqrt(np.nanmean(errs**2))) < 1e-9
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # nothing is overwritten without --force
    code, _, err = run_cli(capsys, *args)
    assert_one_line_error(code, err, "exists")


@pytest.mark.parametrize(
    "case, needle",
    [
        ("refit", "unknown constellation"),
        ("other_robot", "another robot model"),
        ("no_robot", "no robot log"),
    ],
)
def test_bad_input_is_one_line(setup, tmp_path, capsys, case, needle):
    d = setup["dir"]
    rec, calib, extra = d / "b.h5", d / "right.json", []
    if case == "refit":
        extra = ["--refit", "camera,constellation"]
    elif case == "other_robot":
        doc = json.loads((d / "right.json").read_text())
        doc["effects"]["joint_offset"] = [0.0] * 7
        calib = tmp_path / "seven.json"
        calib.write_text(json.dumps(doc))
    else:
        rec = tmp_path / "no_robot.h5"
        write_recording(setup["b"].replace(robot=None), rec)
    code, _, err = run_cli(capsys, "evaluate", rec, "--calibration", calib, *extra)
    assert_one_line_error(code, err, needle)


def test_warnings_leave_out_the_transforms_it_refits(setup, tmp_path, capsys):
    """A calibration that determines camera←base and flange←tool only poorly: `evaluate`
    warns about the transforms it takes from the calibration, not about those it refits."""
    doc = json.loads((setup["dir"] / "right.json").read_text())
    doc["identifiability"]["weak"] = [
        {"parameter": "camera_from_base.tx", "sigma": 5e-5, "tolerance": 2e-5},
        {"parameter": "flange_from_tool.ry", "sigma": 3e-4, "tolerance": 1e-4},
    ]
    calib = tmp_path / "weak.json"
    calib.write_text(json.dumps(doc))
    rec = setup["dir"] / "b.h5"
    code, _, err = run_cli(capsys, "evaluate", rec, "--calibration", calib)
    assert code == 0 and "flange_from_tool.ry" in err and "camera_from_base" not in err
    code, _, err = run_cli(
        capsys, "evaluate", rec, "--calibration", calib, "--refit", "camera,tool"
    )
    assert code == 0 and "warning" not in err
