"""Joint limits of a robot model: the built-ins' data-sheet ranges, a URDF's revolute
``<limit lower upper>`` (continuous joints unlimited), and the limits carried unchanged
through the DH JSON, `urdf_text`, a recording's `/robot/joint_limits` and CALIB.json's
robot document."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from robtraj import Recording, RecordingError, RobotLog, UserError, read_recording, write_recording
from robtraj.importers import read_robot_model, robot_description, write_robot_model
from robtraj.model import abb_irb2400_16, robot_from_log, ur10, urdf_text

DATA = Path(__file__).resolve().parent / "data"
#: [rad] the test URDFs round their limits (to 4 decimals; joint 4 of the ABB: 3.49 for 200°)
URDF_DIGITS = 1e-3


def _model(desc):
    return robot_from_log(desc.robot_log(np.zeros(0), np.zeros((0, desc.n_joints))))


def _recording(log: RobotLog) -> Recording:
    """Three frames of two LEDs at the origin with robot log `log`."""
    return Recording(
        time=np.arange(3) * 0.01,
        frame_index=np.arange(3, dtype=np.uint64),
        led_ids=np.arange(2, dtype=np.int32),
        positions=np.zeros((3, 2, 3)),
        robot=log,
    )


def test_builtin_limits_are_the_data_sheet_ranges():
    np.testing.assert_allclose(np.degrees(ur10().joint_limits), [[-360, 360]] * 6, atol=1e-12)
    abb = [[-180, 180], [-100, 110], [-60, 65], [-200, 200], [-120, 120], [-400, 400]]
    np.testing.assert_allclose(np.degrees(abb_irb2400_16().joint_limits), abb, atol=1e-12)
    # ROS-Industrial's URDF (the built-in's joint angles) carries the same ranges
    urdf = read_robot_model(DATA / "abb_irb2400.urdf")
    np.testing.assert_allclose(urdf.joint_limits, abb_irb2400_16().joint_limits, atol=URDF_DIGITS)


def test_urdf_limits_follow_the_joints_and_continuous_is_unlimited(tmp_path):
    text = (DATA / "ur10.urdf").read_text()
    ur = read_robot_model(DATA / "ur10.urdf", base_link="base")
    assert np.isfinite(ur.joint_limits).all()
    np.testing.assert_allclose(ur.joint_limits[2], [-np.pi, np.pi], atol=URDF_DIGITS)
    np.testing.assert_allclose(ur.joint_limits[5], [-2 * np.pi, 2 * np.pi], atol=URDF_DIGITS)
    # joint 4 continuous, joint 6 without an upper bound
    edited = text.replace('"wrist_1_joint" type="revolute"', '"wrist_1_joint" type="continuous"')
    head, tail = edited.split('name="wrist_3_joint"')
    edited = head + 'name="wrist_3_joint"' + tail.replace('upper="6.2832" ', "", 1)
    (tmp_path / "r.urdf").write_text(edited)
    desc = read_robot_model(tmp_path / "r.urdf", base_link="base")
    np.testing.assert_array_equal(desc.joint_limits[3], [-np.inf, np.inf])
    assert desc.joint_limits[5, 1] == np.inf and np.isfinite(desc.joint_limits[5, 0])
    np.testing.assert_array_equal(desc.joint_limits[:3], ur.joint_limits[:3])


def _urdf_round_trip(tmp_path, robot):
    (tmp_path / "r.urdf").write_text(urdf_text(robot))
    return _model(read_robot_model(tmp_path / "r.urdf"))


@pytest.mark.parametrize("make", [abb_irb2400_16, ur10])
def test_urdf_text_limits_read_back_exactly(tmp_path, make):
    robot = make()
    back = _urdf_round_trip(tmp_path, robot)
    np.testing.assert_array_equal(back.joint_limits, robot.joint_limits)


def test_urdf_text_open_and_unknown_limits_read_back(tmp_path):
    limits = np.asarray(abb_irb2400_16().joint_limits).copy()
    limits[3] = [-np.inf, np.inf]  # continuous
    limits[5, 0] = -np.inf  # one side open
    robot = robot_from_log(
        RobotLog(np.zeros(0), np.zeros((0, 6)), model="abb_irb2400_16", joint_limits=limits)
    )
    text = urdf_text(robot)
    assert 'name="joint_4" type="continuous"' in text
    np.testing.assert_array_equal(_urdf_round_trip(tmp_path, robot).joint_limits, limits)
    # limits not known: every joint continuous, and not known again
    bare = robot_from_log(RobotLog(np.zeros(0), np.zeros((0, 6)), dh=np.asarray(robot.dh)))
    assert bare.joint_limits is None
    assert urdf_text(bare).count('type="continuous"') == 6
    assert _urdf_round_trip(tmp_path, bare).joint_limits is None


@pytest.mark.parametrize("angle_unit", ["rad", "deg"])
def test_dh_json_limits_round_trip(tmp_path, angle_unit):
    desc = read_robot_model(DATA / "abb_irb2400.urdf")
    limits = desc.joint_limits.copy()
    limits[3] = [-np.inf, np.inf]
    desc = type(desc)(**{**desc.__dict__, "joint_limits": limits})
    path = write_robot_model(desc, tmp_path / "r.json", angle_unit=angle_unit)
    doc = json.loads(path.read_text())
    assert doc["joint_limits"][3] == [None, None]
    np.testing.assert_allclose(read_robot_model(path).joint_limits, limits, rtol=1e-15)
    # a built-in written out carries its own limits
    builtin = read_robot_model(write_robot_model(read_robot_model("ur10"), tmp_path / "u.json"))
    np.testing.assert_array_equal(builtin.joint_limits, ur10().joint_limits)


def test_recording_and_calibration_document_carry_the_limits(tmp_path):
    desc = read_robot_model(DATA / "ur10.urdf", base_link="base")
    limits = desc.joint_limits.copy()
    limits[0] = [-np.inf, 1.0]
    log = type(desc)(**{**desc.__dict__, "joint_limits": limits}).robot_log(
        np.arange(3) * 0.01, np.zeros((3, 6))
    )
    rec = _recording(log)
    back = read_recording(write_recording(rec, tmp_path / "r.h5"))
    assert not back.extras
    np.testing.assert_array_equal(back.robot.joint_limits, limits)
    np.testing.assert_array_equal(robot_from_log(back.robot).joint_limits, limits)
    # CALIB.json's "robot" is the log's model document
    doc = json.loads(json.dumps(back.robot.model_document()))
    np.testing.assert_array_equal(robot_description(doc).joint_limits, limits)


@pytest.mark.parametrize(
    "limits, message",
    [
        ([[-1, 1]] * 5, "must hold 6 rows"),
        ([[1, -1]] * 6, "row 0 has lower > upper"),
        ([[-1, 1, 2]] * 6, "row 0 must be"),
        ([[-1, "x"]] * 6, "numbers only"),
    ],
)
def test_bad_dh_json_limits_are_one_line_user_errors(limits, message):
    doc = {"dh": np.asarray(ur10().dh).tolist(), "joint_limits": limits}
    with pytest.raises(UserError, match=message) as e:
        robot_description(doc)
    assert "\n" not in str(e.value)


def test_bad_urdf_and_recording_limits_are_refused(tmp_path):
    text = (DATA / "abb_irb2400.urdf").read_text()
    path = tmp_path / "r.urdf"
    path.write_text(text.replace('lower="-1.0472" upper="1.1345"', 'lower="1.2" upper="1.1"'))
    with pytest.raises(UserError, match="'joint_3' has limits lower 1.2 > upper 1.1"):
        read_robot_model(path)
    for bad in (np.zeros((5, 2)), np.array([[1.0, -1.0]] * 6)):
        log = RobotLog(np.arange(3) * 0.01, np.zeros((3, 6)), model="ur10", joint_limits=bad)
        rec = _recording(log)
        with pytest.raises(RecordingError, match="/robot/joint_limits"):
            write_recording(rec, tmp_path / "bad.h5")
