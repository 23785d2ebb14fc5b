"""Robot models for a recording: built-in names, DH JSON and URDF files (docs/import.md).

The two URDFs under data/ were written for these tests from the robots' public
dimensions, in the styles of ROS-Industrial (abb_irb2400.urdf: link frames parallel to
the base at q = 0, axes along x/y/z) and ur_description (ur10.urdf: origins with rpy,
shoulder and elbow offsets). Their joint senses and zeros turned out to be those of
robtraj's built-in DH tables as published (checked below, no axis sign or zero had to be
changed); the one difference is the UR10's base: the built-in (the controller's) base is
ur_description's `base` frame, base_link turned by π about z, hence ``base_link="base"``.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yourdfpy

from robtraj import (
    Pose,
    Recording,
    RecordingError,
    RobotLog,
    UserError,
    read_recording,
    write_recording,
)
from robtraj.importers import RobotDescription, read_robot_model, write_robot_model
from robtraj.model import (
    BUILTIN_ROBOTS,
    abb_irb2400_16,
    forward_kinematics,
    gravity_torque,
    robot_from_log,
    ur10,
    urdf_text,
)

DATA = Path(__file__).resolve().parent / "data"
ABB, UR10 = DATA / "abb_irb2400.urdf", DATA / "ur10.urdf"
# built-in name, URDF, base link of the URDF that is the built-in's base
ROBOTS = [("abb_irb2400_16", ABB, "base_link"), ("ur10", UR10, "base")]
TOL = 1e-9  # m and rad


def _robot(desc: RobotDescription):
    n = desc.n_joints
    return robot_from_log(desc.robot_log(np.zeros(1), np.zeros((1, n))))


def _fk(robot, q) -> np.ndarray:
    """`(N, 4, 4)` base←flange for joint vectors `q` `(N, J)`."""
    fk = jax.jit(jax.vmap(lambda q: forward_kinematics(robot, q).as_matrix()))
    return np.asarray(fk(jnp.asarray(q, jnp.float64)))


def _errors(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest position [m] and rotation angle [rad] between poses `(N, 4, 4)`."""
    pos = np.abs(a[:, :3, 3] - b[:, :3, 3]).max()
    # ‖Ra − Rb‖_F = 2√2 sin(θ/2): accurate near θ = 0, unlike acos of the trace
    chord = np.linalg.norm(a[:, :3, :3] - b[:, :3, :3], axis=(1, 2)) / (2 * np.sqrt(2))
    return float(pos), float(2 * np.arcsin(np.minimum(chord, 1.0)).max())


def _yourdfpy_fk(path: Path, q: np.ndarray, base: str, flange: str = "tool0") -> np.ndarray:
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)
    out = []
    for qi in q:
        urdf.update_cfg(qi)
        out.append(urdf.get_transform(flange, base))
    return np.array(out)


# ----------------------------------------------------------------------------- the two robots


@pytest.mark.parametrize("name, path, base", ROBOTS)
def test_urdf_gives_the_builtin_robot(name, path, base):
    desc = read_robot_model(path, base_link=base)
    builtin = BUILTIN_ROBOTS[name]()
    q = np.random.default_rng(1).uniform(-np.pi, np.pi, (1000, 6))
    pos, rot = _errors(_fk(_robot(desc), q), _fk(builtin, q))
    assert pos < TOL and rot < TOL, (pos, rot)
    # the construction's conventions (θ offsets in [−π/2, π/2], a common normal through
    # the previous origin for parallel axes) give the published tables themselves
    np.testing.assert_allclose(desc.dh, np.asarray(builtin.dh), atol=1e-12)
    assert desc.model is None and len(desc.joint_names) == 6


def test_urdf_link_masses_and_names():
    abb = read_robot_model(ABB)
    assert abb.name == "abb_irb2400" and abb.joint_names[0] == "joint_1"
    np.testing.assert_array_equal(abb.link_mass, [90.0, 45.0, 35.0, 12.0, 6.0, 1.0])
    ur = read_robot_model(UR10, base_link="base")
    np.testing.assert_array_equal(ur.link_mass, [7.1, 12.7, 4.27, 2.0, 2.0, 0.365])
    torque = gravity_torque(_robot(ur), jnp.zeros(6))
    builtin = robot_from_log(
        RobotLog(np.zeros(1), np.zeros((1, 6)), model="ur10", link_mass=ur.link_mass)
    )
    np.testing.assert_allclose(torque, gravity_torque(builtin, jnp.zeros(6)), atol=1e-9)


@pytest.mark.parametrize("name, path, base", ROBOTS)
def test_urdf_fk_equals_yourdfpy(name, path, base):
    """An independent reference: yourdfpy's own forward kinematics of the file."""
    q = np.random.default_rng(2).uniform(-2 * np.pi, 2 * np.pi, (300, 6))
    ours = _fk(_robot(read_robot_model(path, base_link=base)), q)
    pos, rot = _errors(ours, _yourdfpy_fk(path, q, base))
    assert pos < TOL and rot < TOL, (pos, rot)


def test_the_ur_description_root_is_the_base_turned_by_pi():
    root = _robot(read_robot_model(UR10))  # base_link: x and y of the controller's base negated
    q = np.random.default_rng(3).uniform(-np.pi, np.pi, (50, 6))
    a, b = _fk(root, q), _fk(BUILTIN_ROBOTS["ur10"](), q)
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    np.testing.assert_allclose(a, turn @ b, atol=1e-12)


# ----------------------------------------------------------------------------- DH JSON


def test_dh_json_round_trip(tmp_path):
    desc = read_robot_model(UR10, base_link="base")
    for unit, angle_unit in [("m", "rad"), ("mm", "deg")]:
        path = write_robot_model(
            desc, tmp_path / f"ur10_{unit}.json", unit=unit, angle_unit=angle_unit
        )
        back = read_robot_model(path)
        assert back.name == "ur10" and back.model is None
        np.testing.assert_allclose(back.dh, desc.dh, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(back.flange.position, desc.flange.position, atol=1e-15)
        np.testing.assert_allclose(back.flange.quaternion_wxyz, desc.flange.quaternion_wxyz)
        np.testing.assert_array_equal(back.link_mass, desc.link_mass)


def test_builtin_names_and_their_dh_json(tmp_path):
    desc = read_robot_model("abb_irb2400_16")
    assert desc.model == "abb_irb2400_16" and desc.dh is None and desc.n_joints == 6
    path = write_robot_model(desc, tmp_path / "abb.json")
    q = np.random.default_rng(4).uniform(-np.pi, np.pi, (100, 6))
    pos, rot = _errors(_fk(_robot(read_robot_model(path)), q), _fk(_robot(desc), q))
    assert pos < 1e-15 and rot < 1e-15
    np.testing.assert_array_equal(read_robot_model(path).link_mass, [90, 45, 35, 12, 6, 1])


def test_hand_written_dh_json_in_mm_and_degrees(tmp_path):
    doc = {
        "name": "irb2400",
        "unit": "mm",
        "angle_unit": "deg",
        "dh": [
            [615, 100, -90, 0],
            [0, 705, 0, -90],
            [0, 135, -90, 0],
            [755, 0, 90, 0],
            [0, 0, -90, 0],
            [85, 0, 0, 0],
        ],
        "flange": {"position": [0, 0, 0], "quaternion_wxyz": [0, 0, 0, 1]},
    }
    (tmp_path / "r.json").write_text(json.dumps(doc))
    desc = read_robot_model(tmp_path / "r.json")
    assert desc.link_mass is None
    robot = _robot(desc)
    np.testing.assert_array_equal(robot.link_mass, np.full(6, 5.0))
    q = np.random.default_rng(5).uniform(-np.pi, np.pi, (100, 6))
    pos, rot = _errors(_fk(robot, q), _fk(BUILTIN_ROBOTS["abb_irb2400_16"](), q))
    assert pos < 1e-12 and rot < 1e-12


# ----------------------------------------------------------------------------- generic chains


def _urdf(joints, *, masses=None) -> str:
    """URDF text of a serial chain from `(type, xyz, rpy, axis)` per joint, links l0 …
    (no tool0 or flange link: the last link is the flange); `masses` by link index."""
    masses = masses or {}
    links = [f"l{i}" for i in range(len(joints) + 1)]
    out = ['<?xml version="1.0"?>', '<robot name="chain">']
    for i, link in enumerate(links):
        m = masses.get(i)
        inertial = "" if m is None else f'<inertial><mass value="{m!r}"/></inertial>'
        out.append(f'  <link name="{link}">{inertial}</link>')
    for i, (kind, xyz, rpy, axis) in enumerate(joints):
        axis_xml = "" if axis is None else f'<axis xyz="{" ".join(map(repr, axis))}"/>'
        limit = (
            '<limit lower="-3" upper="3" effort="1" velocity="1"/>' if kind == "revolute" else ""
        )
        out.append(
            f'  <joint name="j{i}" type="{kind}"><parent link="{links[i]}"/>'
            f'<child link="{links[i + 1]}"/><origin xyz="{" ".join(map(repr, xyz))}" '
            f'rpy="{" ".join(map(repr, rpy))}"/>{axis_xml}{limit}</joint>'
        )
    out.append("</robot>")
    return "\n".join(out)


def _random_chain(rng, n_movable: int):
    """Joint 1 about the base z axis (turned and raised), then random revolute,
    continuous and fixed joints (random origins, rpy, axes of any length), a fixed end."""
    yaw = float(rng.uniform(-np.pi, np.pi))
    joints = [("revolute", (0.0, 0.0, float(rng.uniform(0, 1))), (0.0, 0.0, yaw), (0.0, 0.0, 1.0))]
    while sum(j[0] != "fixed" for j in joints) < n_movable or joints[-1][0] != "fixed":
        kind = rng.choice(["revolute", "continuous", "fixed"], p=[0.45, 0.2, 0.35])
        xyz = tuple(float(v) for v in rng.normal(0, 0.3, 3))
        rpy = tuple(float(v) for v in rng.uniform(-np.pi, np.pi, 3))
        axis = rng.normal(size=3)
        axis = tuple(float(v) for v in axis * rng.uniform(0.5, 2) / np.linalg.norm(axis))
        if sum(j[0] != "fixed" for j in joints) >= n_movable:
            kind = "fixed"
        joints.append((str(kind), xyz, rpy, None if kind == "fixed" else axis))
    return joints


def _compare_with_yourdfpy(tmp_path, text: str):
    path = tmp_path / "c.urdf"
    path.write_text(text)
    desc = read_robot_model(path)
    q = np.random.default_rng(6).uniform(-np.pi, np.pi, (200, desc.n_joints))
    last = yourdfpy.URDF.load(str(path), build_scene_graph=False).robot.joints[-1].child
    pos, rot = _errors(_fk(_robot(desc), q), _yourdfpy_fk(path, q, "l0", last))
    assert pos < TOL and rot < TOL, (pos, rot)
    return desc


@pytest.mark.parametrize("seed", range(6))
def test_generic_chain_matches_yourdfpy(tmp_path, seed):
    rng = np.random.default_rng(seed)
    joints = _random_chain(rng, n_movable=int(rng.integers(1, 9)))
    desc = _compare_with_yourdfpy(tmp_path, _urdf(joints))
    assert desc.n_joints == sum(j[0] != "fixed" for j in joints)
    np.testing.assert_array_equal(desc.link_mass, np.full(desc.n_joints, 5.0))


SPECIAL = {
    # j1 and j2 the same line (same sense), j3 parallel to j2 with an offset, j4 the
    # opposite sense of j3 on a parallel line, j5 meets j4, j6 skew
    "coincident-parallel-antiparallel": [
        ("revolute", (0, 0, 0.3), (0, 0, 0.5), (0, 0, 1)),
        ("continuous", (0, 0, 0.2), (0, 0, 0), (0, 0, 1)),
        ("revolute", (0.2, 0.1, 0.0), (0, 0, 0), (0, 0, 1)),
        ("revolute", (0.0, 0.3, 0.1), (0, 0, 0), (0, 0, -1)),
        ("revolute", (0.0, 0.0, 0.4), (0, 0, 0), (1, 0, 0)),
        ("revolute", (0.3, 0.2, 0.1), (0.3, 0.2, 0.1), (0, 1, 0)),
        ("fixed", (0.1, 0, 0.05), (0, 1.0, 0), None),
    ],
    # a 6R with a spherical wrist turned off the base axes, and a bare axis (default x)
    "spherical-wrist": [
        ("revolute", (0, 0, 0.5), (0, 0, 0), (0, 0, 1)),
        ("revolute", (0.15, 0, 0), (0.4, 0, 0), (0, 1, 0)),
        ("fixed", (0.0, 0, 0.3), (0, 0, 0.7), None),
        ("revolute", (0.0, 0, 0.3), (0, 0, 0), (0, -1, 0)),
        ("revolute", (0.1, 0, 0.1), (0, 0, 0), None),
        ("revolute", (0.4, 0, 0), (0, 0, 0), (0, 1, 0)),
        ("revolute", (0, 0, 0), (0, 0, 0), (1, 0, 0)),
        ("fixed", (0.08, 0, 0), (0, np.pi / 2, 0), None),
    ],
    "one-joint": [
        ("revolute", (0, 0, 0), (0, 0, 0), (0, 0, 1)),
        ("fixed", (0.1, 0.2, 0.3), (1, 2, 3), None),
    ],
}


@pytest.mark.parametrize("case", sorted(SPECIAL))
def test_special_axis_arrangements_match_yourdfpy(tmp_path, case):
    _compare_with_yourdfpy(tmp_path, _urdf(SPECIAL[case]))


def test_link_masses_fold_fixed_children_and_default_to_5_kg(tmp_path):
    """l0 is the base (not counted); l3 is fixed to l2; l4 … l6 give none; l8, fixed to
    l7, is the flange link: its mass is the payload's."""
    masses = {0: 50.0, 1: 3.0, 2: 4.0, 3: 1.5, 7: 0.25, 8: 0.5}
    desc = _compare_with_yourdfpy(tmp_path, _urdf(SPECIAL["spherical-wrist"], masses=masses))
    np.testing.assert_array_equal(desc.link_mass, [3.0, 5.5, 5.0, 5.0, 5.0, 0.25])
    assert desc.payload_mass == 0.5


GRIPPER = """<link name="finger"><inertial><mass value="0.3"/>
<inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial></link>
<joint name="finger_joint" type="prismatic"><parent link="tool0"/><child link="finger"/>
<axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>"""


def test_a_gripper_beyond_the_flange_is_payload_not_a_chain(tmp_path):
    """Joints beyond the flange link (a gripper's fingers) belong to the tool: left out
    of the chain, their links' masses part of the payload."""
    plain = read_robot_model(ABB)
    desc = read_robot_model(_abb_with(tmp_path, GRIPPER))
    np.testing.assert_array_equal(desc.dh, plain.dh)
    assert desc.payload_mass == pytest.approx((plain.payload_mass or 0.0) + 0.3)


@pytest.mark.parametrize("make", [abb_irb2400_16, ur10])
def test_urdf_text_reads_back_as_the_same_robot(tmp_path, make):
    """`urdf_text` then `read_robot_model`: the same DH table, flange, link masses and
    payload, so the same kinematics and gravity torques (against the built-in)."""
    robot = make()
    (tmp_path / "r.urdf").write_text(urdf_text(robot))
    back = robot_from_log(
        read_robot_model(tmp_path / "r.urdf").robot_log(np.zeros(2), np.zeros((2, 6)))
    )
    np.testing.assert_allclose(back.dh, robot.dh, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.link_mass, robot.link_mass, rtol=0, atol=1e-12)
    assert float(back.payload_mass) == pytest.approx(float(robot.payload_mass), abs=1e-12)
    q = jnp.asarray(np.random.default_rng(4).uniform(-3, 3, (200, 6)))
    for fn in (lambda r, qq: forward_kinematics(r, qq).as_matrix(), gravity_torque):
        got, want = (np.asarray(jax.vmap(lambda qq, r=r: fn(r, qq))(q)) for r in (back, robot))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * max(1.0, np.abs(want).max()))


@pytest.mark.parametrize(
    "first",
    [
        ((0, 0, 0), (0, 0, 0), (0, 0, -1)),  # along −z
        ((0.1, 0, 0.2), (0, 0, 0), (0, 0, 1)),  # off the origin
        ((0, 0, 0), (0.2, 0, 0), (0, 0, 1)),  # tilted
    ],
)
def test_a_first_axis_off_the_base_z_axis_is_refused(tmp_path, first):
    path = tmp_path / "c.urdf"
    path.write_text(_urdf([("revolute", *first), ("revolute", (0, 0, 0.4), (0, 0, 0), (0, 1, 0))]))
    with pytest.raises(UserError, match="not the base z axis") as e:
        read_robot_model(path)
    assert "\n" not in str(e.value)


# ----------------------------------------------------------------------------- bad input


def _abb_with(tmp_path, extra: str = "", replace: tuple[str, str] = ("", "")) -> Path:
    text = ABB.read_text().replace(*replace).replace("</robot>", extra + "</robot>")
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    return path


def _write(tmp_path, text: str) -> Path:
    (tmp_path / "bad.urdf").write_text(text)
    return tmp_path / "bad.urdf"


BRANCH = """<link name="cam"/><joint name="cam_pan" type="revolute"><parent link="link_3"/>
<child link="cam"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"""


@pytest.mark.parametrize(
    "make, kwargs, message",
    [
        (lambda t: _abb_with(t, BRANCH), {}, "several movable chains"),
        (lambda t: _abb_with(t), {"flange_link": "nope"}, "no link named 'nope'"),
        (lambda t: _abb_with(t), {"base_link": "link_2"}, "moves with joint 'joint_1'"),
        (lambda t: _abb_with(t, replace=('"joint_4" type="revolute"', '"joint_4" type="prismatic"')), {}, "prismatic"),
        (lambda t: _abb_with(t, replace=('<axis xyz="1 0 0"/>\n    <limit lower="-3.49"', '<mimic joint="joint_3"/><axis xyz="1 0 0"/>\n    <limit lower="-3.49"')), {}, "mimics 'joint_3'"),
        (lambda t: _abb_with(t, replace=('type="revolute"', 'type="fixed"')), {}, "no revolute joint"),
        (lambda t: _abb_with(t, replace=('<link name="tool0"/>', '<link name="tool0"/><link name="tool0"/>')), {}, "link 'tool0' is defined twice"),
        (lambda t: _abb_with(t, replace=('<child link="base"/>', '<child link="link_6"/>')), {}, "'link_6' is the child of two joints"),
        (lambda t: _abb_with(t, replace=("</robot>", "</robo")), {}, "not well-formed XML"),
        (lambda t: _abb_with(t, replace=('<child link="link_4"/>', '<child link="link_x"/>')), {}, "'link_x', which is not defined"),
        (lambda t: _write(t, '<robo name="x"><link name="a"/></robo>'), {}, "not a URDF"),
    ],
)  # fmt: skip
def test_bad_urdf_is_one_line_user_error(tmp_path, make, kwargs, message):
    path = make(tmp_path)
    with pytest.raises(UserError, match=message) as e:
        read_robot_model(path, **kwargs)
    assert "\n" not in str(e.value)


def test_no_flange_link_and_a_branching_end_is_refused(tmp_path):
    joints = SPECIAL["one-joint"]
    text = _urdf(joints).replace(
        "</robot>",
        '<link name="a"/><joint name="fa" type="fixed"><parent link="l1"/><child link="a"/>'
        '</joint><link name="b"/><joint name="fb" type="fixed"><parent link="l1"/>'
        '<child link="b"/></joint></robot>',
    )
    (tmp_path / "c.urdf").write_text(text)
    with pytest.raises(UserError, match="cannot tell the flange link"):
        read_robot_model(tmp_path / "c.urdf")
    desc = read_robot_model(tmp_path / "c.urdf", flange_link="b")
    assert desc.n_joints == 1


@pytest.mark.parametrize(
    "doc, message",
    [
        ({"dh": [[0.1, 0.2, 0.0, 0.0], [0.1, 0.2, 0.0]]}, "dh row 1 has 3 numbers, expected 4"),
        ({"dh": []}, "at least one row"),
        ({"dh": [[0.1, 0.2, 0.0, 0.0]], "units": "mm"}, "unknown key 'units'"),
        ({"dh": [[615, 100, 0.0, 0.0]]}, "millimetres need"),
        ({"dh": [[0.6, 0.1, 90, 0.0]]}, "degrees need"),
        ({"dh": [[0.6, 0.1, 0, 0]], "unit": "inch"}, "length unit 'inch'"),
        ({"dh": [[0.6, 0.1, 0, 0]], "link_mass": [1, 2]}, "link_mass must hold 1 masses"),
        ({"dh": [[0.6, 0.1, 0, "x"]]}, "numbers only"),
        ({"dh": [[0.6, 0.1, 0, 0]], "flange": {"position": [0, 0, 0], "quaternion_wxyz": [1, 1, 0, 0]}}, "not unit"),
        ("[1, 2", "not valid JSON"),
    ],
)  # fmt: skip
def test_bad_dh_json_is_one_line_user_error(tmp_path, doc, message):
    path = tmp_path / "r.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(UserError, match=message) as e:
        read_robot_model(path)
    assert "\n" not in str(e.value)


def test_unknown_spec_names_the_builtins(tmp_path):
    with pytest.raises(UserError, match="abb_irb2400_16, ur10"):
        read_robot_model("irb9999")


# ----------------------------------------------------------------------------- recordings


def _recording(robot: RobotLog) -> Recording:
    n, m = 4, 2
    return Recording(
        time=np.arange(n) * 0.01,
        frame_index=np.arange(n, dtype=np.uint64),
        led_ids=np.arange(m, dtype=np.int32),
        positions=np.zeros((n, m, 3)),
        robot=robot,
    )


def test_recording_round_trip_with_flange_and_link_mass(tmp_path):
    desc = read_robot_model(UR10, base_link="base")
    joints = np.random.default_rng(7).uniform(-np.pi, np.pi, (5, 6))
    path = write_recording(
        _recording(desc.robot_log(np.arange(5) * 0.008, joints)), tmp_path / "r.h5"
    )
    back = read_recording(path)
    log = back.robot
    assert log.model is None and not back.extras and not back.extra_attrs
    np.testing.assert_array_equal(log.dh, desc.dh)
    np.testing.assert_array_equal(log.flange.position, desc.flange.position)
    np.testing.assert_array_equal(log.flange.quaternion_wxyz, desc.flange.quaternion_wxyz)
    np.testing.assert_array_equal(log.link_mass, desc.link_mass)
    robot = robot_from_log(log)
    np.testing.assert_array_equal(robot.link_mass, desc.link_mass)
    pos, rot = _errors(_fk(robot, joints), _fk(BUILTIN_ROBOTS["ur10"](), joints))
    assert pos < TOL and rot < TOL
    again = read_recording(write_recording(back, tmp_path / "s.h5"))  # copies keep them
    np.testing.assert_array_equal(again.robot.link_mass, desc.link_mass)


def test_builtin_model_with_flange_and_masses_replaced():
    flange = Pose(np.array([0.0, 0.0, 0.1]), np.array([1.0, 0.0, 0.0, 0.0]))
    log = RobotLog(np.zeros(1), np.zeros((1, 6)), model="ur10", flange=flange, link_mass=np.ones(6))
    robot = robot_from_log(log)
    assert robot.name == "ur10"
    np.testing.assert_array_equal(robot.link_mass, np.ones(6))
    q = np.zeros((1, 6))
    shift = _fk(robot, q)[0, :3, 3] - _fk(BUILTIN_ROBOTS["ur10"](), q)[0, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(shift), 0.1, atol=1e-12)
    bare = robot_from_log(RobotLog(np.zeros(1), np.zeros((1, 6)), dh=np.zeros((6, 4))))
    np.testing.assert_array_equal(bare.link_mass, np.full(6, 5.0))
    assert float(bare.payload_mass) == 1.0


@pytest.mark.parametrize(
    "change, message",
    [
        ({"link_mass": np.ones(5)}, "/robot/link_mass"),
        ({"link_mass": -np.ones(6)}, "/robot/link_mass"),
        ({"flange": Pose(np.zeros(3), np.array([1.0, 1.0, 0.0, 0.0]))}, "/robot/flange"),
        ({"flange": Pose(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]]))}, "/robot/flange"),
    ],
)
def test_bad_flange_or_link_mass_is_refused(tmp_path, change, message):
    log = RobotLog(np.arange(3) * 0.01, np.zeros((3, 6)), dh=np.zeros((6, 4)), **change)
    with pytest.raises(RecordingError, match=message):
        write_recording(_recording(log), tmp_path / "r.h5")
