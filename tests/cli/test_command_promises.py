"""Each command keeps its promise: bad input is one line and exit 2 before any computation,
no output is overwritten without --force, a failure leaves nothing partial, and a result
without meaning is refused or warned about."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import (
    assert_one_line_error,
    digest,
    run_cli,
    small_recording,
    valid_calibration,
    write_small,
)

from robtraj.cli import _output
from robtraj.recording import write_recording


def _forbid(monkeypatch, target: str) -> None:
    """Make `target` ("module:attr") fail if called: the command must stop before it."""
    module, attr = target.split(":")

    def called(*a, **k):
        raise AssertionError(f"{target} ran before the inputs were checked")

    monkeypatch.setattr(f"{module}.{attr}", called)


HEAVY = [
    "robtraj.sim:simulate",
    "robtraj.sim:simulate_to",
    "robtraj.estimate:estimate_poses",
    "robtraj.estimate.calibration:fit",
    "robtraj.estimate._base_frame:base_frame_poses",
    "robtraj.analysis.discrepancy:discover",
    "robtraj.importers:import_file",
]


@pytest.fixture
def forbid_computation(monkeypatch):
    for t in HEAVY:
        _forbid(monkeypatch, t)


@pytest.fixture
def inputs(tmp_path):
    rec = write_small(tmp_path / "rec.h5")
    calib = tmp_path / "calib.json"
    calib.write_text(json.dumps(valid_calibration()))
    return rec, calib


# ----------------------------------------------------------------------------- CALIB.json


def _calib_case(case: str, doc: dict, tmp_path):
    path = tmp_path / "c.json"
    if case == "list":
        path.write_text(json.dumps([doc]))
    elif case == "2-element position":
        doc["camera_from_base"]["position"] = [0.1, 1.0]
        path.write_text(json.dumps(doc))
    elif case == "zero quaternion":
        doc["flange_from_tool"]["quaternion_wxyz"] = [0, 0, 0, 0]
        path.write_text(json.dumps(doc))
    elif case == "hdf5 recording":
        path = tmp_path / "c.h5"
        write_recording(small_recording(), path)
    return path


@pytest.mark.parametrize(
    ("case", "needle"),
    [
        ("list", "JSON object"),
        ("2-element position", "camera_from_base.position must be 3"),
        ("zero quaternion", "norm 0"),
        ("hdf5 recording", "an HDF5 file"),
    ],
)
@pytest.mark.parametrize("command", ["iso9283", "report"])
def test_bad_calibration_is_one_line(
    tmp_path, capsys, inputs, forbid_computation, case, needle, command
):
    rec, _ = inputs
    path = _calib_case(case, valid_calibration(), tmp_path)
    before = digest(path)
    extra = ["--out", tmp_path / "r"] if command == "report" else []
    code, _, err = run_cli(capsys, command, rec, "--calibration", path, *extra)
    assert_one_line_error(code, err, str(path), needle)
    assert digest(path) == before


# ----------------------------------------------------------------------------- output folders


@pytest.mark.parametrize(
    "args",
    [
        ["poses", "{rec}", "-o", "{missing}/p.h5"],
        ["simulate", "{missing}/s.h5"],
        ["calibrate", "{rec}", "-o", "{missing}/c.json"],
        ["import", "{src}", "-o", "{missing}/i.h5"],
        ["iso9283", "{rec}", "--calibration", "{calib}", "--json", "{missing}/i.json"],
        ["demo", "--out", "{missing}/demo"],
    ],
    ids=lambda a: a[0],
)
def test_output_into_a_missing_folder_refused_before_computing(
    tmp_path, capsys, inputs, forbid_computation, args
):
    rec, calib = inputs
    src = tmp_path / "x.n3d"
    src.write_bytes(b"\x00" * 64)
    missing = tmp_path / "no" / "such"
    values = {"rec": rec, "calib": calib, "src": src, "missing": missing}
    code, _, err = run_cli(capsys, *[a.format(**values) for a in args])
    assert_one_line_error(code, err, "does not exist")
    assert not (tmp_path / "no").exists()


@pytest.mark.parametrize("command", ["simulate", "demo"])
def test_negative_seed_is_one_line(tmp_path, capsys, forbid_computation, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    args = ["simulate", "s.h5"] if command == "simulate" else ["demo", "--out", "d"]
    code, _, err = run_cli(capsys, *args, "--seed", "-1")
    assert_one_line_error(code, err, "seed must be >= 0")
    assert list(tmp_path.iterdir()) == []  # the demo leaves no empty folder


# ----------------------------------------------------------------------------- no overwrite


@pytest.mark.parametrize(
    ("args", "existing"),
    [
        (["poses", "{rec}", "-o", "{d}/new.h5", "--json", "{d}/old"], "file"),
        (["calibrate", "{rec}", "-o", "{d}/new.json", "--json", "{d}/old"], "file"),
        (["iso9283", "{rec}", "--calibration", "{calib}", "--json", "{d}/old"], "file"),
        (["deviation", "{rec}", "--calibration", "{calib}", "--json", "{d}/old"], "file"),
        (
            ["report", "{rec}", "--calibration", "{calib}", "--out", "{d}/r", "--json", "{d}/old"],
            "file",
        ),
        (["report", "{rec}", "--calibration", "{calib}", "--out", "{d}/old"], "folder"),
        (["demo", "--out", "{d}/old"], "folder"),
        (["simulate", "{d}/old"], "file"),
        (["discrepancy", "{rec}", "--report", "{d}/old"], "folder"),
    ],
    ids=lambda a: a[0] if isinstance(a, list) else a,
)
def test_existing_output_is_refused_without_force(
    tmp_path, capsys, inputs, forbid_computation, args, existing
):
    rec, calib = inputs
    d = tmp_path / "out"
    d.mkdir()
    old = d / "old"
    if existing == "file":
        old.write_text("earlier result")
    else:
        old.mkdir()
        (old / "report.html").write_text("earlier report")
    before = digest(d)
    code, _, err = run_cli(capsys, *[a.format(rec=rec, calib=calib, d=d) for a in args])
    assert_one_line_error(code, err, str(old), "--force")
    assert digest(d) == before


def test_new_file_and_new_folder_leave_nothing_on_failure(tmp_path):
    target = tmp_path / "a.json"
    target.write_text("old")
    with pytest.raises(RuntimeError), _output.new_file(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError
    assert target.read_text() == "old" and sorted(tmp_path.iterdir()) == [target]
    folder = tmp_path / "report"
    with pytest.raises(RuntimeError), _output.new_folder(folder) as tmp:
        (tmp / "report.html").write_text("half")
        raise RuntimeError
    assert sorted(tmp_path.iterdir()) == [target]
    with _output.new_folder(folder) as tmp:
        (tmp / "report.html").write_text("v1")
        (tmp / "keep.png").write_text("png")
    # --force into the folder: same-named files replaced, others kept, nothing else touched
    (folder / "user-notes.txt").write_text("mine")
    with _output.new_folder(folder) as tmp:
        (tmp / "report.html").write_text("v2")
    assert (folder / "report.html").read_text() == "v2"
    assert (folder / "keep.png").exists() and (folder / "user-notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "report"]


def test_report_failure_leaves_no_partial_folder(tmp_path, capsys, inputs, monkeypatch):
    """A failure while the report is written leaves neither the folder nor a temporary one."""
    rec, calib = inputs
    calls = []

    def failing_report(out, *a, **k):
        (out / "report.html").write_text("half")
        calls.append(out)
        raise RuntimeError("disk trouble")

    monkeypatch.setattr("robtraj.report.recording_report", failing_report)
    monkeypatch.setattr(
        "robtraj.cli._analysis_inputs.load",
        lambda args, need_program=True: (small_recording(), None, None),
    )
    with pytest.raises(RuntimeError, match="disk trouble"):
        run_cli(capsys, "report", rec, "--calibration", calib, "--out", tmp_path / "rep")
    assert calls and not (tmp_path / "rep").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# ----------------------------------------------------------------------------- 2 LEDs


def test_calibrate_with_two_leds_seen_says_so(tmp_path, capsys, forbid_computation):
    rec = small_recording(n=50, m=6)
    pos = rec.positions.copy()
    pos[:, 2:] = np.nan
    write_recording(rec.replace(positions=pos), tmp_path / "two.h5")
    for cmd in (["calibrate", tmp_path / "two.h5", "-o", tmp_path / "c.json"],
                ["discrepancy", tmp_path / "two.h5"]):  # fmt: skip
        code, _, err = run_cli(capsys, *cmd)
        assert_one_line_error(code, err, "at most 2 LEDs seen", "at least 3")
    assert not (tmp_path / "c.json").exists()
