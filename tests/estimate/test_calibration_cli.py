"""`robtraj calibrate`: CALIB.json contents, refusal to overwrite, one-line errors."""

import json

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


def test_bad_input_is_one_line_and_exit_2(recording, tmp_path, capsys):
    out = tmp_path / "c.json"
    assert main(["calibrate", str(tmp_path / "missing.h5"), "-o", str(out)]) == 2
    assert main(["calibrate", str(recording), "-o", str(out), "--estimate", "warp_drive"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("robtraj: error:") for line in err)
    assert "warp_drive" in err[1]
    assert not out.exists()
