"""`robtraj attach`: a campaign's parts joined into one recording; every part that does
not fit is one line `robtraj: error: …`, exit 2, and nothing is written."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli

from robtraj import read_recording
from robtraj.sim import CONTROLLER_EPOCH, simulate, write_campaign

SHIFT = 7.3


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("attach")
    sim = simulate("calibration", seed=2, duration=16.0, rate=125.0)
    files = write_campaign(sim, tmp, clock_offset=SHIFT)
    other = simulate("iso_cube", seed=9, duration=16.0, rate=125.0)
    (tmp / "other").mkdir()
    other_files = write_campaign(other, tmp / "other", clock_offset=SHIFT)
    return tmp, files, other_files, sim


def _options(files, **changes) -> dict:
    opts = {
        "--robot-log": files.robot_log, "--mapping": files.mapping, "--robot": files.robot,
        "--tool": files.tool, "--program": files.program,
    }  # fmt: skip
    opts.update({f"--{k.replace('_', '-')}": v for k, v in changes.items()})
    return opts


def _base(files, **changes) -> list:
    args = [files.tracker]
    for flag, value in _options(files, **changes).items():
        args += [flag, value]
    return args


def test_attach_joins_every_part(capsys, parts):
    tmp, files, _, sim = parts
    out = tmp / "run.h5"
    code, stdout, err = run_cli(capsys, "attach", *_base(files), "-o", out)
    assert code == 0, err
    rec = read_recording(out)
    # the joint log on the tracker clock: the controller's samples less the found offset
    assert abs(rec.robot.clock_offset - (CONTROLLER_EPOCH + SHIFT)) < 2e-3
    assert rec.robot.clock_offset_sigma > 0
    np.testing.assert_allclose(rec.robot.joints, sim.robot.joints, rtol=0, atol=1e-10)
    np.testing.assert_allclose(
        rec.robot.time, sim.robot.time + (CONTROLLER_EPOCH + SHIFT - rec.robot.clock_offset),
        rtol=0, atol=1e-6,
    )  # fmt: skip
    np.testing.assert_array_equal(rec.tool.led_ids, sim.tool.led_ids)
    np.testing.assert_allclose(rec.tool.normals, sim.tool.normals, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        rec.tool.flange_from_tool.position, sim.tool.flange_from_tool.position, atol=1e-15
    )
    np.testing.assert_array_equal(rec.program.motion, sim.program.motion)
    np.testing.assert_allclose(
        rec.program.targets.quaternion_wxyz, sim.program.targets.quaternion_wxyz, atol=1e-15
    )
    np.testing.assert_array_equal(rec.positions, sim.positions)
    assert "tool.json" in rec.attrs["attached"]
    # a second attach of what the file holds already is refused
    code, _, err = run_cli(capsys, "attach", out, "--tool", files.tool, "-o", tmp / "again.h5")
    assert_one_line_error(code, err, "already holds a tool")
    assert not (tmp / "again.h5").exists()


def test_a_known_offset_skips_the_search(capsys, parts):
    tmp, files, _, _ = parts
    out = tmp / "given.h5"
    args = _base(files, clock_offset=CONTROLLER_EPOCH + SHIFT)
    code, _, err = run_cli(capsys, "attach", *args, "-o", out)
    assert code == 0, err
    rec = read_recording(out)
    assert rec.robot.clock_offset == CONTROLLER_EPOCH + SHIFT and rec.robot.clock_offset_sigma == 0


def _log_without_time(tmp, files, other):
    path = tmp / "no_time.csv"
    lines = files.robot_log.read_text().splitlines()
    path.write_text("\n".join(";".join(r.split(";")[1:]) for r in lines) + "\n")
    return {"robot_log": path}


def _five_joints(tmp, files, other):
    mapping = json.loads(files.mapping.read_text())
    mapping["joints"] = mapping["joints"][:5]
    path = tmp / "five.json"
    path.write_text(json.dumps(mapping))
    return {"mapping": path}


def _no_chain_urdf(tmp, files, other):
    path = tmp / "broken.urdf"
    text = files.robot.read_text().replace('"tool0"', '"tool9"')
    path.write_text(text)
    return {"robot": path, "flange_link": "tool0"}


def _unknown_base_link(tmp, files, other):
    return {"base_link": "nope"}


def _foreign_tool(tmp, files, other):
    doc = json.loads(files.tool.read_text())
    doc["led_ids"] = [i + 100 for i in doc["led_ids"]]
    doc["reference_leds"] = [i + 100 for i in doc["reference_leds"]]
    path = tmp / "foreign_tool.json"
    path.write_text(json.dumps(doc))
    return {"tool": path}


def _other_run(tmp, files, other):
    return {"robot_log": other.robot_log, "mapping": other.mapping}


def _log_of_the_day_before(tmp, files, other):
    path = tmp / "yesterday.csv"
    rows = files.robot_log.read_text().splitlines()
    out = [rows[0]]
    for r in rows[1:]:
        t, rest = r.split(";", 1)
        out.append(f"{float(t.replace(',', '.')) - 86400e3:.3f}".replace(".", ",") + ";" + rest)
    path.write_text("\n".join(out) + "\n")
    return {"robot_log": path, "clock_offset": CONTROLLER_EPOCH + SHIFT}


@pytest.mark.parametrize(
    "change, needle",
    [
        (_log_without_time, "time_ms"),
        (_five_joints, "5 joints"),
        (_no_chain_urdf, "no link named 'tool0'"),
        (_unknown_base_link, "no link named 'nope'"),
        (_foreign_tool, "not in the stream"),
        (_other_run, "does not match the tracker stream"),
        (_log_of_the_day_before, "does the log overlap the stream"),
    ],
)
def test_parts_that_do_not_fit_are_one_line_errors(capsys, parts, change, needle):
    tmp, files, other, _ = parts
    out = tmp / f"bad_{change.__name__}.h5"
    args = _base(files, **change(tmp, files, other))
    code, _, err = run_cli(capsys, "attach", *args, "-o", out)
    assert_one_line_error(code, err, needle)
    assert not out.exists()
