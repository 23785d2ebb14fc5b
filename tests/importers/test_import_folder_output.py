"""``robtraj import FOLDER -o OUT``: several series go into a folder (an -o ending in .h5 is
refused), a folder holding a single series may be written to one .h5 file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from robtraj import read_recording
from robtraj.cli import main

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
IPA = SHARED / "ipa-robot-accuracy"
pytestmark = pytest.mark.skipif(not IPA.is_dir(), reason="shared data not present")
SERIES = [
    "Series_A_measurements_grid.h5",
    "Series_B_calibration_handeye.h5",
    "Series_B_measurements_joint_configurations.h5",
]


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("robtraj: error: "), err
    return err


@pytest.mark.parametrize("name", ["B.h5", "B.H5", "B.hdf5"])
def test_several_series_into_a_file_name_is_refused(tmp_path, capsys, name):
    out = tmp_path / name
    assert main(["import", str(IPA), "-o", str(out), "--preset", "ipa-ur10"]) == 2
    err = _err(capsys)
    assert "3 pose series" in err and "name a folder" in err
    assert list(tmp_path.iterdir()) == []  # no folder B.h5, no temporary left


def test_several_series_into_an_existing_file_is_refused(tmp_path, capsys):
    out = tmp_path / "results"
    out.write_text("keep")
    argv = ["import", str(IPA), "-o", str(out), "--preset", "ipa-ur10", "--force"]
    assert main(argv) == 2
    assert "name a folder" in _err(capsys)
    assert out.read_text() == "keep"


def test_several_series_into_a_folder(tmp_path, capsys):
    out = tmp_path / "B"
    assert main(["import", str(IPA), "-o", str(out), "--preset", "ipa-ur10"]) == 0
    assert sorted(p.name for p in out.iterdir()) == SERIES
    assert capsys.readouterr().out.count("wrote ") == 3
    # into the same folder again: refused without --force, replaced with it
    assert main(["import", str(IPA), "-o", str(out), "--preset", "ipa-ur10"]) == 2
    assert "earlier results" in _err(capsys)
    assert main(["import", str(IPA), "-o", str(out), "--preset", "ipa-ur10", "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == SERIES


def test_a_single_series_folder_into_a_file(tmp_path, capsys):
    src = IPA / "Series_A"  # one .csv (and two .txt)
    out = tmp_path / "A.h5"
    assert main(["import", str(src), "-o", str(out), "--preset", "ipa-ur10"]) == 0
    assert out.is_file()
    assert capsys.readouterr().out.startswith(f"wrote {out}: ")
    flat = tmp_path / "flat.h5"
    csv = src / "measurements_grid.csv"
    assert main(["import", str(csv), "-o", str(flat), "--preset", "ipa-ur10"]) == 0
    a, b = read_recording(out), read_recording(flat)
    assert a.n_frames == b.n_frames > 0
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.robot.joints, b.robot.joints)
    capsys.readouterr()
    assert main(["import", str(src), "-o", str(out), "--preset", "ipa-ur10"]) == 2
    assert "exists" in _err(capsys)
    assert main(["import", str(src), "-o", str(out), "--preset", "ipa-ur10", "--force"]) == 0
    assert out.is_file()


def test_a_single_series_folder_into_a_folder(tmp_path):
    out = tmp_path / "A"
    assert main(["import", str(IPA / "Series_A"), "-o", str(out), "--preset", "ipa-ur10"]) == 0
    assert [p.name for p in out.iterdir()] == ["measurements_grid.h5"]


def test_a_single_series_folder_into_a_folder_named_h5_is_refused(tmp_path, capsys):
    src = tmp_path / "src"
    shutil.copytree(IPA / "Series_A", src)
    out = tmp_path / "A.h5"
    out.mkdir()
    assert main(["import", str(src), "-o", str(out), "--preset", "ipa-ur10"]) == 2
    assert "is a folder; name a file" in _err(capsys)
    assert list(out.iterdir()) == []
