"""``robtraj import``: one line and exit 2 on bad input, never overwrite without --force."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robtraj import read_recording
from robtraj.cli import main

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
N3D = SHARED / "optotrak-n3d-probe" / "kinematics_sample_optotrak.n3d"
IPA = SHARED / "ipa-robot-accuracy"
NATNET = SHARED / "natnet-packets"
pytestmark = pytest.mark.skipif(not SHARED.is_dir(), reason="shared data not present")


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("robtraj: error: ")
    return err


def test_n3d_with_preset_and_force(tmp_path, capsys):
    out = tmp_path / "a.h5"
    assert main(["import", str(N3D), "-o", str(out), "--preset", "optotrak-probe"]) == 0
    rec = read_recording(out)
    assert rec.n_leds == 41 and list(rec.tool.led_ids) == list(range(6))
    capsys.readouterr()
    assert main(["import", str(N3D), "-o", str(out)]) == 2
    assert "exists" in _err(capsys)
    assert main(["import", str(N3D), "-o", str(out), "--force", "--rate", "35"]) == 0
    rec = read_recording(out)
    assert rec.tool is None and rec.time[1] == pytest.approx(1 / 35)


def test_pose_csv_folder_and_flags(tmp_path, capsys):
    out = tmp_path / "ipa"
    assert main(["import", str(IPA), "-o", str(out), "--preset", "ipa-ur10"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "Series_A_measurements_grid.h5",
        "Series_B_calibration_handeye.h5",
        "Series_B_measurements_joint_configurations.h5",
    ]
    rec = read_recording(out / "Series_B_calibration_handeye.h5")
    assert rec.n_frames == 25 and rec.robot is None
    # the same series through column flags instead of the preset
    flags = ["--position-cols", "measurement_x,measurement_y,measurement_z",
             "--rotation-cols", "measurement_rx,measurement_ry,measurement_rz",
             "--position-unit", "mm", "--angle-unit", "deg", "--euler", "XYZ",
             "--delimiter", ";", "--decimal", ","]  # fmt: skip
    flat = tmp_path / "flat.h5"
    src = IPA / "Series_B" / "calibration_handeye.csv"
    assert main(["import", str(src), "-o", str(flat), *flags]) == 0
    np.testing.assert_allclose(read_recording(flat).positions, rec.positions)


def test_natnet_capture(tmp_path):
    cap = tmp_path / "cap.bin"
    cap.write_bytes((NATNET / "mocapframe_packet_v3.bin").read_bytes())
    out = tmp_path / "n.h5"
    assert main(["import", str(cap), "-o", str(out), "--model-id", "2"]) == 0
    rec = read_recording(out)
    assert list(rec.led_ids) == [1, 2, 3, 4, 5] and rec.visible.all()


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["nope.n3d"], "no such file"),
        (["{tmp}/x.xyz"], "cannot tell the format"),
        (["{n3d}", "--mapping", "m.json"], "do not apply to n3d"),
        (["{n3d}", "--preset", "ipa-ur10"], "unknown n3d preset"),
        (["{n3d}", "--constellation", "nope.json"], "no such constellation"),
        (["{tmp}/short.n3d"], "truncated"),
        (["{csv}"], "needs a column mapping"),
        (["{csv}", "--preset", "nope"], "unknown preset"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, argv, needle):
    (tmp_path / "x.xyz").write_text("hello")
    (tmp_path / "short.n3d").write_bytes(N3D.read_bytes()[:1000])
    csv = IPA / "Series_B" / "calibration_handeye.csv"
    argv = [a.format(tmp=tmp_path, n3d=N3D, csv=csv) for a in argv]
    assert main(["import", *argv, "-o", str(tmp_path / "o.h5")]) == 2
    assert needle in _err(capsys)
    assert not (tmp_path / "o.h5").exists()
