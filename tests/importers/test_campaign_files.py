"""A campaign's program and tool files (docs/campaign.md), and the program segments
`attach` derives from the joint log, against the simulator's own."""

import json

import numpy as np
import pytest

from robtraj._errors import UserError
from robtraj.estimate import tool_poses
from robtraj.importers import load_constellation, program_csv, read_program, tool_document
from robtraj.importers._attach import program_segments
from robtraj.model import abb_irb2400_16
from robtraj.sim import simulate


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _matrix(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@pytest.fixture(scope="module")
def sim():
    return simulate("iso_cube", seed=1, duration=60.0, rate=250.0)


def test_program_csv_round_trip(tmp_path, sim):
    path = tmp_path / "program.csv"
    path.write_text(program_csv(sim.program))
    program, extra = read_program(path)
    np.testing.assert_allclose(program.targets.position, sim.program.targets.position, atol=0)
    np.testing.assert_allclose(
        program.targets.quaternion_wxyz, sim.program.targets.quaternion_wxyz, atol=1e-15
    )
    np.testing.assert_array_equal(program.motion, sim.program.motion)
    np.testing.assert_array_equal(program.speed, sim.program.speed)
    assert "label" in extra and program.segment is None


def test_kuka_abc_ur_rotvec_and_millimetres(tmp_path):
    """KUKA's A, B, C [deg] are R = Rz(A)·Ry(B)·Rx(C); UR's rotation vector is the axis
    times the angle; x_mm and speed_mm_s are millimetres."""
    (tmp_path / "kuka.csv").write_text(
        "label;x_mm;y_mm;z_mm;a;b;c;motion;speed_mm_s;cycle\n"
        "P0;1000;0;1200;10;-20;30;PTP;0;1\n"
        "P1;1100;50;1150;-45;5;170;LIN;250;1\n"
    )
    program, extra = read_program(tmp_path / "kuka.csv")
    np.testing.assert_allclose(program.targets.position[1], [1.1, 0.05, 1.15])
    for q, (a, b, c) in zip(program.targets.quaternion_wxyz, [(10, -20, 30), (-45, 5, 170)]):
        want = _rz(np.deg2rad(a)) @ _ry(np.deg2rad(b)) @ _rx(np.deg2rad(c))
        np.testing.assert_allclose(_matrix(q), want, atol=1e-12)
    assert list(program.motion) == ["start", "linear"] and program.speed[1] == 0.25
    assert list(extra["label"]) == ["P0", "P1"] and list(extra["cycle"]) == [1, 1]

    axis, angle = np.array([0.0, 0.6, 0.8]), 1.2
    (tmp_path / "ur.csv").write_text(
        "x,y,z,rx,ry,rz,motion\n0.5,0.1,0.4,0,0,0,movej\n"
        f"0.6,0.1,0.4,{axis[0] * angle},{axis[1] * angle},{axis[2] * angle},movel\n"
    )
    program, _ = read_program(tmp_path / "ur.csv")
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rodrigues = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    np.testing.assert_allclose(_matrix(program.targets.quaternion_wxyz[1]), rodrigues, atol=1e-12)


def test_json_program(tmp_path):
    doc = {"unit": "mm", "targets": [
        {"position": [500, 0, 900], "quaternion_wxyz": [1, 0, 0, 0], "motion": "start"},
        {"position": [600, 0, 900], "quaternion_wxyz": [0, 1, 0, 0], "motion": "linear",
         "speed": 0.1, "label": "P2"},
    ]}  # fmt: skip
    (tmp_path / "p.json").write_text(json.dumps(doc))
    program, _ = read_program(tmp_path / "p.json")
    np.testing.assert_allclose(program.targets.position, [[0.5, 0, 0.9], [0.6, 0, 0.9]])
    np.testing.assert_allclose(program.targets.quaternion_wxyz[1], [0, 1, 0, 0])


@pytest.mark.parametrize(
    "text, needle",
    [
        ("x,y,z,motion\n0,0,0,joint\n1,0,0,joint\n", "no orientation columns"),
        ("a,b,c\n0,0,0\n1,1,1\n", "no position columns"),
        ("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n1,0,0,2,0,0,0\n", "not of unit length"),
        ("x,y,z,qw,qx,qy,qz,motion\n0,0,0,1,0,0,0,joint\n1,0,0,1,0,0,0,circ\n", "motion 'circ'"),
        (
            "x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n1,zero,0,1,0,0,0\n",
            "target 2 has no number in column 'y'",
        ),
        ("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n", "at least two targets"),
    ],
)
def test_bad_programs_are_one_line_errors(tmp_path, text, needle):
    (tmp_path / "bad.csv").write_text(text)
    with pytest.raises(UserError, match=needle) as e:
        read_program(tmp_path / "bad.csv")
    assert "\n" not in str(e.value)


def test_tool_json_round_trip_with_normals_and_tcp(tmp_path, sim):
    (tmp_path / "tool.json").write_text(json.dumps(tool_document(sim.tool)))
    tool = load_constellation(tmp_path / "tool.json")
    np.testing.assert_array_equal(tool.led_ids, sim.tool.led_ids)
    np.testing.assert_allclose(tool.constellation, sim.tool.constellation, atol=0)
    np.testing.assert_allclose(tool.normals, sim.tool.normals, atol=1e-15)
    np.testing.assert_array_equal(tool.reference_leds, sim.tool.reference_leds)
    np.testing.assert_allclose(tool.flange_from_tool.position, sim.tool.flange_from_tool.position)


def test_tool_csv_with_normals_in_millimetres(tmp_path):
    (tmp_path / "tool.csv").write_text(
        "id,x_mm,y_mm,z_mm,nx,ny,nz\n1,0,0,0,0,0,2\n2,50,0,0,0,0,1\n3,0,50,0,1,0,1\n"
    )
    tool = load_constellation(tmp_path / "tool.csv")
    np.testing.assert_allclose(tool.constellation[1], [0.05, 0, 0])
    np.testing.assert_allclose(tool.normals[2], [np.sqrt(0.5), 0, np.sqrt(0.5)])
    (tmp_path / "bad.csv").write_text(
        "id,x,y,z,nx,ny,nz\n1,0,0,0,0,0,0\n2,1,0,0,0,0,1\n3,0,1,0,0,0,1\n"
    )
    with pytest.raises(UserError, match="non-zero"):
        load_constellation(tmp_path / "bad.csv")


@pytest.mark.parametrize("scenario", ["iso_cube", "paper", "calibration"])
def test_program_segments_from_the_joint_log_match_the_simulators(scenario):
    """The segment of each frame (the last target whose move has started), found from the
    joint log alone, agrees with the simulator's own bookkeeping except where a move's
    first samples are still below the rest thresholds (≤ 3 % of the frames)."""
    rec = simulate(scenario, seed=2, duration=60.0, rate=100.0)
    tcp = tool_poses(abb_irb2400_16(), rec.robot.joints, rec.tool.flange_from_tool)
    # the simulated log runs on the robot clock (tracker + τ = 0 here)
    segment, reached = program_segments(rec.time, rec.robot.time, tcp, rec.program.targets)
    assert segment is not None and reached >= 2
    assert np.mean(segment != rec.program.segment) < 0.03
    # the dwells, where ISO 9283 reads the segment, agree everywhere
    moving = np.abs(np.gradient(rec.robot.joints, rec.robot.time, axis=0)).max(1) > 1e-9
    still = np.interp(rec.time, rec.robot.time, moving.astype(float)) == 0
    assert still.mean() > 0.2
    assert np.all(segment[still] == rec.program.segment[still])


def test_another_program_gives_no_segments(sim):
    other = simulate("calibration", seed=1, duration=30.0, rate=50.0)
    tcp = tool_poses(abb_irb2400_16(), sim.robot.joints, sim.tool.flange_from_tool)
    segment, _ = program_segments(sim.time, sim.robot.time, tcp, other.program.targets)
    assert segment is None
