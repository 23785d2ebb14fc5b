"""`robtraj calibrate`: CALIB.json contents, refusal to overwrite, one-line errors."""

import json
from pathlib import Path

import pytest

from robtraj import write_recording
from robtraj.cli import main
from robtraj.sim import simulate


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("cal") / "rec.h5"
    write_recording(simulate("calibration", seed=3, duration=16.0, rate=25.0), path)
    return path


def test_writes_calib_json_and_refuses_to_overwrite(recording, tmp_path, capsys):
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(recording), "-o", str(out), "--robust", "huber"]) == 0
    doc = json.loads(out.read_text())
    assert set(doc["camera_from_base"]) == {"position", "quaternion_wxyz"}
    assert set(doc["flange_from_tool"]) == {"position", "quaternion_wxyz"}
    assert len(doc["constellation"]["led_ids"]) == len(doc["constellation"]["positions"]) == 18
    n = len(doc["covariance"]["parameters"])
    assert n == 12 + 3 * 18 and len(doc["covariance"]["matrix"]) == n
    assert doc["residual_rms_m"] < 200e-6 and doc["time_offset"] == 0.0
    assert doc["gauge"]["kind"] == "reference_constellation" and doc["robust"] == "huber"
    assert "wrote" in capsys.readouterr().out

    assert main(["calibrate", str(recording), "-o", str(out)]) == 2
    assert "exists" in capsys.readouterr().err


def test_a_solve_that_stops_early_says_so_and_exits_3(recording, tmp_path, capsys):
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(recording), "-o", str(out), "--max-steps", "2"]) == 3
    doc = json.loads(out.read_text())
    assert doc["converged"] is False and "2 steps" in doc["convergence"]
    assert "NOT converged" in capsys.readouterr().out


def test_bad_input_is_one_line_and_exit_2(recording, tmp_path, capsys):
    out = tmp_path / "c.json"
    assert main(["calibrate", str(tmp_path / "missing.h5"), "-o", str(out)]) == 2
    assert main(["calibrate", str(recording), "-o", str(out), "--estimate", "warp_drive"]) == 2
    assert main(["calibrate", str(recording), "-o", str(out), "--motion-threshold", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("robtraj: error:") for line in err)
    assert "warp_drive" in err[1] and "motion threshold" in err[2]
    assert not out.exists()


_POSE_CSV = (
    Path(__file__).resolve().parents[2].parent
    / "shared"
    / "data"
    / "ipa-robot-accuracy"
    / "Series_B"
    / "measurements_joint_configurations.csv"
)


@pytest.mark.exhaustive
@pytest.mark.skipif(not _POSE_CSV.is_file(), reason="ipa-robot-accuracy data not present")
def test_calibrates_a_recording_imported_from_pose_csv(tmp_path, capsys):
    """6-DOF pose observations (`robtraj import --format pose-csv`): the tool frame is the
    probed one, the virtual points get uniform weights (they carry no noise of their own)
    and the fit with link lengths converges (exit 0). About a minute, most of it
    compilation."""
    src = tmp_path / "poses.csv"
    src.write_text("".join(_POSE_CSV.read_text().splitlines(keepends=True)[:301]))
    rec = tmp_path / "rec.h5"
    args = ["import", str(src), "-o", str(rec), "--format", "pose-csv", "--preset", "ipa-ur10"]
    assert main(args) == 0
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(rec), "-o", str(out), "--estimate", "link_length"]) == 0
    doc = json.loads(out.read_text())
    assert doc["converged"] and doc["convergence"]
    assert doc["noise_model"]["kind"] == "uniform"
    assert "weights: uniform" in capsys.readouterr().out
    assert doc["gauge"]["kind"] == "probe"
    # the nominal UR10 explains the probe poses to about a millimetre (docs/real_ur10.md)
    assert doc["residual_rms_m"] < 3e-3


def test_a_joint_angle_error_map_from_simulate_to_calibrate_and_evaluate(tmp_path, capsys):
    """`simulate --effect joint2_map=V` hides a constant map (a joint-2 offset of V);
    `calibrate --estimate joint2_map` fits the map under its prior, says it in words and
    writes it to CALIB.json, where it recovers V over the angles the arm reached within
    3 posterior σ; `evaluate` takes the calibration back."""
    import numpy as np

    from robtraj.model import map_active

    rec = tmp_path / "rec.h5"
    value = 3e-4
    args = ["--scenario", "calibration", "--duration", "16", "--rate", "25", "--seed", "3"]
    assert main(["simulate", str(rec), *args, "--effect", f"joint2_map={value}"]) == 0
    assert "joint2_map=[256 values" in capsys.readouterr().out
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(rec), "-o", str(out), "--estimate", "joint2_map"]) == 0
    printed = capsys.readouterr().out
    assert "joint 2 angle error map: rms" in printed
    doc = json.loads(out.read_text())
    c = np.asarray(doc["effects"]["joint2_map"])
    assert c.shape == (256,)
    from robtraj import read_recording

    q2 = np.asarray(read_recording(rec).robot.joints)[:, 1]
    knots = np.unique(map_active(q2)[0])
    names = doc["covariance"]["parameters"]
    idx = [names.index(f"joint2_map.k{k:03d}") for k in knots]
    sigma = np.sqrt(np.diag(np.asarray(doc["covariance"]["matrix"]))[idx])
    assert np.all(np.abs(c[knots] - value) <= 3 * sigma + 1e-12), (c[knots], sigma)
    assert main(["evaluate", str(rec), "--calibration", str(out)]) == 0


def test_calibrate_starts_from_a_calibration_and_holds_its_effects(recording, tmp_path, capsys):
    """`calibrate --init CALIB.json`: the start's effects not in --estimate are held at
    its values (here a joint offset the recording does not carry, so the fit would move
    it), the provenance names the start; a start of another robot is one line, exit 2."""
    import numpy as np

    first = tmp_path / "first.json"
    assert main(["calibrate", str(recording), "-o", str(first), "--estimate", "joint_offset"]) == 0
    doc = json.loads(first.read_text())
    held = np.asarray(doc["effects"]["joint_offset"]) + np.array([0, 2e-4, 0, 0, 0, 0])
    doc["effects"]["joint_offset"] = held.tolist()
    start = tmp_path / "start.json"
    start.write_text(json.dumps(doc))
    out = tmp_path / "out.json"
    assert main(["calibrate", str(recording), "-o", str(out), "--init", str(start)]) == 0
    res = json.loads(out.read_text())
    np.testing.assert_allclose(res["effects"]["joint_offset"], held, rtol=0, atol=1e-15)
    assert res["provenance"] == {
        "command": "calibrate",
        "init": str(start),
        "init_provenance": {},
    }
    capsys.readouterr()
    doc["robot"] = {"model": "ur10"}
    other = tmp_path / "other.json"
    other.write_text(json.dumps(doc))
    code = main(["calibrate", str(recording), "-o", str(tmp_path / "x.json"), "--init", str(other)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "calibrated robot 'ur10'" in err[0], err
