"""Close the loop on the simulator, through the CLI: a robot with hidden compliance,
link length and joint offset errors is calibrated with those effects (`calibrate
--estimate`; that `discrepancy --calibration-out` names them and writes the same kind of
CALIB.json is `tests/analysis/test_named_model.py`'s); `compensate` corrects its ISO
cube program; the same robot runs the corrected program (`simulate --commanded`) and
`iso9283` shows what is left. With a controller that attains its targets exactly
(`--ideal-controller`) that is the calibration's own error: AP ≤ 0.5·RP + 20 µm at every
pose. With the cube's injected controller errors it is exactly those approach and drift
errors, which no model of the robot describes. A target beyond the recorded robot's
joint limits is refused by name."""

import dataclasses
import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, run_cli

from robtraj import read_recording, write_recording
from robtraj.analysis.compensation import compensate
from robtraj.calibration_file import load_calibration
from robtraj.model import robot_from_log
from robtraj.sim import iso_cube_truth

DURATION, RATE = 120.0, 50.0
HIDDEN = [
    "--effect", "joint_compliance=1.5e-6",
    "--effect", "link_length=0,0,0,3e-4,0,0,0,0,0,0,0,0",
    "--effect", "joint_offset=0,0,4e-4,0,0,0",
]  # fmt: skip
#: [m] per component: AP after compensation against the injected floor. The mean of ≥ 5
#: dwells has a standard error of ≤ 3 µm (RP ≈ 40–60 µm is mostly the two approach
#: directions, S_l ≈ 2–5 µm); the calibration's TCP prediction adds a few µm. 15 µm is
#: ~3 σ of both together.
TOLERANCE = 15e-6


def _cli(*args) -> int:
    from robtraj.cli import main

    return main([str(a) for a in args])


def _iso(tmp, name, *extra):
    rec = tmp / f"{name}.h5"
    args = ["--scenario", "iso_cube", "--seed", 1, "--duration", DURATION, "--rate", RATE]
    assert _cli("simulate", rec, *args, *HIDDEN, "--no-truth", *extra) == 0
    out = tmp / f"{name}.json"
    # exit 1: characteristics a short test cannot determine (named on stderr)
    assert _cli("iso9283", rec, "--calibration", tmp / "calib.json", "--json", out) in (0, 1)
    return json.loads(out.read_text())["poses"], rec


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("compensate")
    cal, calib = tmp / "cal.h5", tmp / "calib.json"
    args = ["--scenario", "calibration", "--seed", 1, "--duration", 40, "--rate", 100]
    assert _cli("simulate", cal, *args, *HIDDEN, "--no-truth") == 0
    effects = "joint_compliance,link_length,joint_offset"
    assert _cli("calibrate", cal, "--estimate", effects, "-o", calib) == 0
    return tmp


@pytest.fixture(scope="module")
def loop(calibrated):
    tmp = calibrated
    before, rec = _iso(tmp, "iso")
    corrected = tmp / "corrected.csv"
    assert _cli("compensate", rec, "--calibration", tmp / "calib.json", "-o", corrected) == 0
    after, _ = _iso(tmp, "iso_compensated", "--commanded", corrected)
    return tmp, before, after


def test_compensation_brings_the_accuracy_to_the_repeatability(calibrated):
    """A controller that attains what it is sent: after compensation AP ≤ 0.5·RP + 20 µm at
    every pose (from several tenths of a millimetre), RP unchanged."""
    tmp = calibrated
    before, rec = _iso(tmp, "ideal", "--ideal-controller")
    corrected = tmp / "ideal_corrected.csv"
    assert _cli("compensate", rec, "--calibration", tmp / "calib.json", "-o", corrected) == 0
    after, _ = _iso(tmp, "ideal_compensated", "--ideal-controller", "--commanded", corrected)
    for name in ("P1", "P2", "P3", "P4", "P5"):
        assert before[name]["AP_mm"] > 0.3, name
        assert after[name]["AP_mm"] <= 0.5 * after[name]["RP_mm"] + 0.020, (name, after[name])
        # RP ≈ 10 µm from ~5 dwells: its standard error is ~2.5 µm
        assert after[name]["RP_mm"] == pytest.approx(before[name]["RP_mm"], abs=5e-3)


def test_compensation_leaves_only_the_unmodelled_approach_error(loop):
    _, before, after = loop
    truth = iso_cube_truth(DURATION, 1e-4)
    for name in ("P1", "P2", "P3", "P4", "P5"):
        ap = np.array([after[name][f"AP{c}_mm"] for c in "xyz"]) * 1e-3
        assert before[name]["AP_mm"] > 0.3  # the hidden effects are there
        assert np.all(np.abs(ap - truth[name]["AP_vector"]) < TOLERANCE), (name, ap)
        # repeatability is the robot's, not the program's
        assert after[name]["RP_mm"] == pytest.approx(before[name]["RP_mm"], rel=0.1, abs=2e-3)


def test_a_calibration_of_another_robot_is_refused(capsys, loop):
    tmp = loop[0]
    doc = json.loads((tmp / "calib.json").read_text())
    doc["robot"] = {"model": "ur10"}
    (tmp / "ur10.json").write_text(json.dumps(doc))
    out = tmp / "never.csv"
    code, _, err = run_cli(
        capsys, "compensate", tmp / "iso.h5", "--calibration", tmp / "ur10.json", "-o", out
    )
    assert_one_line_error(code, err, "another robot")
    assert not out.exists()


def test_a_target_beyond_a_joint_limit_is_refused_by_name(capsys, loop):
    """The ISO cube recording with a joint limit in its `/robot` that one of its poses
    needs to pass: refused, the first target that needs it and the joint named, nothing
    written."""
    tmp = loop[0]
    rec = read_recording(tmp / "iso.h5")
    robot = robot_from_log(rec.robot)
    res = compensate(
        rec.program,
        robot,
        load_calibration(tmp / "calib.json"),
        rec.tool.flange_from_tool,
        rec.robot.joints[0],
    )
    # the upper limit of one joint between its largest angle (several visits of a pose
    # share it) and the next: the first target that needs more is refused
    reach = np.maximum(res.nominal_joints, res.joints)
    below = [np.max(q[q < q.max() - 1e-6]) for q in reach.T]
    joint = int(np.argmax(reach.max(0) - below))
    limits = np.asarray(robot.joint_limits).copy()
    limits[joint, 1] = 0.5 * (reach[:, joint].max() + below[joint])
    worst = int(np.flatnonzero(reach[:, joint] > limits[joint, 1])[0])
    limited = dataclasses.replace(rec, robot=dataclasses.replace(rec.robot, joint_limits=limits))
    path = write_recording(limited, tmp / "limited.h5")
    out = tmp / "never_limited.csv"
    code, _, err = run_cli(
        capsys, "compensate", path, "--calibration", tmp / "calib.json", "-o", out
    )
    assert_one_line_error(code, err, f"target {worst + 1} put joint {joint + 1} at", "joint limits")
    assert not out.exists()


def test_the_predicted_accuracy_after_compensation_is_what_compensation_gives(loop):
    """From the uncompensated recording and its calibration alone, the AP vector each
    pose will have after compensation (`accuracy_after_compensation`) is the one the
    compensated run measures, within `TOLERANCE` per component; the AP it starts from is
    the measured one, and the stated σ is of the size of the calibration's TCP error
    (a few µm, > 0)."""
    from robtraj.analysis import accuracy_after_compensation
    from robtraj.cli._iso9283 import iso_of
    from robtraj.estimate import base_frame_poses

    tmp, before, after = loop
    rec = read_recording(tmp / "iso.h5")
    calib = load_calibration(tmp / "calib.json")
    iso = iso_of(rec, base_frame_poses(rec, calib))
    pred = accuracy_after_compensation(rec, calib, iso)
    for k, name in enumerate(pred.names):
        now = np.array([before[name][f"AP{c}_mm"] for c in "xyz"]) * 1e-3
        np.testing.assert_allclose(pred.error_now[k], now, atol=1e-9)
        got = np.array([after[name][f"AP{c}_mm"] for c in "xyz"]) * 1e-3
        assert np.all(np.abs(pred.error_after[k] - got) < TOLERANCE), (
            name,
            pred.error_after[k],
            got,
        )
        assert 0 < pred.sigma_after[k] < 20e-6


def test_the_report_shows_the_accuracy_after_compensation(loop):
    """The report's section (`compensation_part`): its figure, its table of AP now and
    predicted per pose with σ, and the summary's worst predicted AP."""
    from robtraj.cli._iso9283 import iso_of
    from robtraj.estimate import base_frame_poses
    from robtraj.report._compensation_section import compensation_part

    tmp = loop[0]
    rec = read_recording(tmp / "iso.h5")
    calib = load_calibration(tmp / "calib.json")
    part = compensation_part(tmp, rec, calib, iso_of(rec, base_frame_poses(rec, calib)))
    assert part.section.title == "Accuracy after compensation (predicted)"
    assert (tmp / "compensation.png").stat().st_size > 10_000
    rows = part.section.tables[0].rows
    assert [r[0] for r in rows] == ["P1", "P2", "P3", "P4", "P5", "P6"]
    assert all(r[2] < 0.1 * r[1] and 0 < r[3] < 0.02 for r in rows)  # mm
    ((label, value),) = part.facts
    assert label.startswith("AP after compensation, predicted, worst")
