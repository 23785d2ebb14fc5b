"""Recording schema 1: plain-h5py files read, malformed files rejected, CLI errors."""

import subprocess
import sys

import h5py
import numpy as np
import pytest

from robtraj import Recording, RecordingError, read_recording, write_recording
from robtraj.cli import main


def _plain_file(path, n=5, m=3, **over):
    """A minimal schema-1 recording written with plain h5py (no robtraj writer)."""
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(n, m, 3))
    pos[1, 2] = np.nan
    data = {
        "tracker/time": np.arange(n) * 0.001,
        "tracker/frame_index": np.arange(n, dtype=np.uint64),
        "tracker/led_ids": np.arange(1, m + 1, dtype=np.int32),
        "tracker/positions": pos,
        "robot/time": np.arange(4) * 0.004,
        "robot/joints": np.zeros((4, 6)),
    }
    attrs = {"schema": "robtraj.recording", "schema_version": 1, "source": "device"}
    for k, v in over.items():
        if k.startswith("attr:"):
            attrs[k[5:]] = v
        elif v is None:
            data.pop(k)
        else:
            data[k] = v
    with h5py.File(path, "w") as f:
        f.attrs.update(attrs)
        for k, v in data.items():
            f.create_dataset(k, data=v)
        f["robot"].attrs["model"] = "abb_irb2400_16"
        f.create_group("vendor/extra").create_dataset("blob", data=np.arange(3))
    return path, data


def test_plain_h5py_file_reads(tmp_path):
    path, data = _plain_file(tmp_path / "p.h5")
    rec = read_recording(path)
    np.testing.assert_array_equal(rec.positions, data["tracker/positions"])
    np.testing.assert_array_equal(rec.visible[1], [True, True, False])
    assert rec.robot.model == "abb_irb2400_16"
    assert rec.tool is None and rec.truth is None and rec.status is None


def test_unknown_groups_survive_a_round_trip(tmp_path):
    path, _ = _plain_file(tmp_path / "p.h5")
    rec = read_recording(path)
    out = write_recording(rec, tmp_path / "q.h5")
    with h5py.File(out) as f:
        np.testing.assert_array_equal(f["vendor/extra/blob"][()], np.arange(3))
    assert isinstance(read_recording(out), Recording)


@pytest.mark.parametrize(
    "over, message",
    [
        ({"attr:schema": "something.else"}, "/schema"),
        ({"attr:schema_version": 2}, "newer"),
        ({"tracker/positions": None}, "/tracker/positions"),
        ({"tracker/positions": np.zeros((5, 2, 3))}, "/tracker/positions"),
        ({"tracker/time": np.array([0, 1, 1, 2, 3.0]) * 1e-3}, "/tracker/time"),
        ({"robot/joints": np.zeros((3, 6))}, "/robot/joints"),
    ],
)
def test_malformed_files_are_rejected_with_the_dataset_named(tmp_path, over, message):
    path, _ = _plain_file(tmp_path / "bad.h5", **over)
    with pytest.raises(RecordingError, match=message):
        read_recording(path)


def test_non_unit_quaternion_is_rejected(tmp_path):
    path, _ = _plain_file(tmp_path / "q.h5")
    with h5py.File(path, "a") as f:
        f["tool/led_ids"] = np.arange(1, 4, dtype=np.int32)
        f["tool/constellation"] = np.zeros((3, 3))
        f["tool/flange_from_tool/position"] = np.zeros(3)
        f["tool/flange_from_tool/quaternion_wxyz"] = np.array([1.0, 0.1, 0, 0])
    with pytest.raises(RecordingError, match="/tool/flange_from_tool/quaternion_wxyz"):
        read_recording(path)


def test_writer_never_overwrites(tmp_path):
    path, _ = _plain_file(tmp_path / "p.h5")
    rec = read_recording(path)
    with pytest.raises(Exception, match="exists"):
        write_recording(rec, path)
    assert read_recording(path).n_frames == 5  # the original is intact


def test_cli_bad_input_is_one_line_exit_2(tmp_path, capsys):
    path, _ = _plain_file(tmp_path / "bad.h5", **{"attr:schema_version": 7})
    code = main(["poses", str(path), "-o", str(tmp_path / "o.h5")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("robtraj: error:")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    code = main(["poses", str(tmp_path / "junk.h5"), "-o", str(tmp_path / "o.h5")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "not a readable HDF5" in err
    assert not (tmp_path / "o.h5").exists()


def test_console_command_help_and_missing_file():
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "robtraj",
            "poses",
            "/nonexistent.h5",
            "-o",
            "/nonexistent-dir/x.h5",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == "robtraj: error: /nonexistent.h5: no such file"
    r = subprocess.run([sys.executable, "-m", "robtraj", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "simulate" in r.stdout
