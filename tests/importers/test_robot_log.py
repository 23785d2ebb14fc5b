"""Robot joint logs (robtraj.importers.read_joint_log) from real files written in tmp_path.

Each reader must give back the joint angles and times the test wrote, converted from
degrees / milliseconds / ISO 8601 / (sec, nanosec) independently here.
"""

from __future__ import annotations

import calendar
import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from robtraj import UserError
from robtraj.importers import JointLog, read_joint_log

UR = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]
UR += ["wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]


def _angles(rng: np.random.Generator, k: int, j: int = 6) -> np.ndarray:
    return rng.uniform(-np.pi, np.pi, (k, j))


# ---------------------------------------------------------------- UR RTDE


def _write_rtde(
    path: Path, time: np.ndarray, actual: np.ndarray, target: np.ndarray | None, sep: str = " "
) -> None:
    """The layout of Universal Robots' record_data.py: a header of RTDE field names."""
    cols = ["timestamp"]
    cols += [f"target_q_{i}" for i in range(6)] if target is not None else []
    cols += [f"actual_q_{i}" for i in range(6)] + [f"actual_qd_{i}" for i in range(6)]
    cols += ["runtime_state"]
    lines = [sep.join(cols)]
    for k in range(time.size):
        row = [time[k]] + (list(target[k]) if target is not None else []) + list(actual[k])
        row += [0.0] * 6 + [2]
        lines.append(sep.join(repr(float(v)) if not isinstance(v, int) else str(v) for v in row))
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("sep", [" ", ","])
def test_ur_rtde(tmp_path: Path, sep: str) -> None:
    rng = np.random.default_rng(0)
    time = 4711.25 + 0.008 * np.arange(40)
    actual, target = _angles(rng, 40), _angles(rng, 40)
    path = tmp_path / "robot_data.csv"
    _write_rtde(path, time, actual, target, sep)
    log = read_joint_log(path)
    assert isinstance(log, JointLog)
    np.testing.assert_array_equal(log.time, time)
    np.testing.assert_array_equal(log.joints, actual)
    np.testing.assert_array_equal(log.commanded, target)
    assert log.names == tuple(UR)
    assert log.source == "ur-rtde"


def test_ur_rtde_without_target_and_renamed(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    time, actual = 0.002 * np.arange(10), _angles(rng, 10)
    path = tmp_path / "log.csv"
    _write_rtde(path, time, actual, None)
    log = read_joint_log(path, joint_names=[f"j{i}" for i in range(6)])
    assert log.commanded is None
    assert log.names == tuple(f"j{i}" for i in range(6))
    np.testing.assert_array_equal(log.joints, actual)
    with pytest.raises(UserError, match="3 joint names given for 6 joint columns"):
        read_joint_log(path, joint_names=["a", "b", "c"])


# ---------------------------------------------------------------- generic CSV + mapping


def _kuka(tmp_path: Path) -> tuple[Path, dict, np.ndarray, np.ndarray, np.ndarray]:
    """KUKA-RSI-like: ';' separated, ',' decimal mark, degrees, milliseconds, a preamble."""
    rng = np.random.default_rng(2)
    t_ms = 1_000_000 + 4 * np.arange(30)
    deg = np.round(rng.uniform(-170, 170, (30, 6)), 6)
    cmd = np.round(rng.uniform(-170, 170, (30, 6)), 6)
    axes = [f"A{i}" for i in range(1, 7)]
    lines = ["RSI trace, IPOC-Zeit in ms", ";".join(["ZEIT_ms", *axes, *[f"S{a}" for a in axes]])]
    for k in range(30):
        cells = [str(t_ms[k])] + [repr(float(v)).replace(".", ",") for v in (*deg[k], *cmd[k])]
        lines.append(";".join(cells))
    path = tmp_path / "rsi.csv"
    path.write_text("\n".join(lines) + "\n")
    mapping = {
        "time": "ZEIT_ms",
        "time_unit": "ms",
        "joints": axes,
        "commanded": [f"S{a}" for a in axes],
        "unit": "deg",
        "delimiter": ";",
        "decimal": ",",
        "skip_rows": 1,
    }
    return path, mapping, t_ms, deg, cmd


def test_kuka_rsi_mapping(tmp_path: Path) -> None:
    path, mapping, t_ms, deg, cmd = _kuka(tmp_path)
    log = read_joint_log(path, mapping=mapping)
    np.testing.assert_allclose(log.time, t_ms / 1000.0, rtol=1e-15, atol=0)
    np.testing.assert_allclose(log.joints, np.deg2rad(deg), rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(log.commanded, np.deg2rad(cmd), rtol=1e-15, atol=1e-15)
    assert log.names == tuple(mapping["joints"]) and log.source == "csv"
    names = [f"axis_{i}" for i in range(6)]
    assert read_joint_log(path, mapping={**mapping, "names": names}).names == tuple(names)


def test_abb_iso8601_mapping_file(tmp_path: Path) -> None:
    """ABB-signal-log-like: ISO 8601 times (nanosecond fractions, offsets), radians."""
    rng = np.random.default_rng(3)
    k = 25
    ns = np.arange(k) * 4_000_123  # 4.000123 ms steps, digits beyond microseconds
    q = _angles(rng, k)
    base = calendar.timegm((2024, 3, 1, 12, 0, 0))  # 2024-03-01T12:00:00Z
    lines = ["Time,Joint 1,Joint 2,Joint 3,Joint 4,Joint 5,Joint 6,Signal"]
    for i in range(k):
        sec, frac = divmod(int(ns[i]), 10**9)
        stamp = f"2024-03-01T12:00:{sec:02d}.{frac:09d}Z"
        if i % 2:  # the same instant written in local time with its offset
            stamp = f"2024-03-01T13:00:{sec:02d}.{frac:09d}+01:00"
        lines.append(",".join([f'"{stamp}"', *(repr(float(v)) for v in q[i]), "1"]))
    path = tmp_path / "abb_signals.csv"
    path.write_text("\n".join(lines) + "\n")
    mapping = tmp_path / "abb.json"
    cols = [f"Joint {i}" for i in range(1, 7)]
    mapping.write_text(json.dumps({"time": "Time", "time_format": "iso8601", "joints": cols}))
    log = read_joint_log(path, mapping=mapping)
    np.testing.assert_allclose(log.time, base + ns / 1e9, rtol=0, atol=5e-7)
    np.testing.assert_allclose(np.diff(log.time), np.diff(ns) / 1e9, rtol=0, atol=5e-7)
    np.testing.assert_array_equal(log.joints, q)
    assert log.commanded is None and log.names == tuple(cols)


# ---------------------------------------------------------------- ROS bags

TYPES2 = get_typestore(Stores.ROS2_HUMBLE)
TYPES1 = get_typestore(Stores.ROS1_NOETIC)
JS = "sensor_msgs/msg/JointState"


def _write_bag(path: Path, storage: str, messages: list[tuple]) -> Path:
    """`messages`: (topic, receive_ns, stamp_ns, names, positions) or (topic, receive_ns, text)."""
    types = TYPES1 if storage == "ros1" else TYPES2
    t = types.types
    if storage == "ros1":
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        conns = {}
        for m in messages:
            msgtype = JS if len(m) == 5 else "std_msgs/msg/String"
            if m[0] not in conns:
                conns[m[0]] = writer.add_connection(m[0], msgtype, typestore=types)
            if len(m) == 3:
                msg = t["std_msgs/msg/String"](data=m[2])
            else:
                sec, nanosec = divmod(m[2], 10**9)
                stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
                header = (
                    t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="")
                    if storage == "ros1"
                    else t["std_msgs/msg/Header"](stamp=stamp, frame_id="")
                )
                empty = np.zeros(0)
                msg = t[JS](
                    header=header,
                    name=list(m[3]),
                    position=np.asarray(m[4], float),
                    velocity=empty,
                    effort=empty,
                )
            data = (types.serialize_ros1 if storage == "ros1" else types.serialize_cdr)(
                msg, msgtype
            )
            writer.write(conns[m[0]], m[1], data)
    return path


def _bag_path(tmp_path: Path, storage: str) -> Path:
    return tmp_path / ("log.bag" if storage == "ros1" else f"bag_{storage}")


ARM = [f"joint_{i}" for i in range(1, 7)]
T0 = 1_700_000_000 * 10**9 + 123_456_789  # header stamp of the first message [ns]


def _arm_messages(
    rng: np.random.Generator, k: int, topic: str = "/joint_states", zero_stamps: bool = False
) -> tuple[list[tuple], np.ndarray, np.ndarray]:
    """Messages with the arm joints shuffled differently in each, plus a gripper joint."""
    stamps = T0 + np.arange(k) * 2_000_000 + rng.integers(0, 1000, k)
    q = _angles(rng, k)
    msgs = []
    for i in range(k):
        names = [*ARM, "gripper_finger_joint"]
        values = [*q[i], 0.04]
        order = rng.permutation(7)
        msgs.append(
            (
                topic,
                int(stamps[i]) + 1_500_000,
                0 if zero_stamps else int(stamps[i]),
                [names[o] for o in order],
                [values[o] for o in order],
            )
        )
    return msgs, stamps, q


def _ns_to_s(ns: np.ndarray) -> np.ndarray:
    return np.array([int(n) // 10**9 + (int(n) % 10**9) / 1e9 for n in ns])


@pytest.mark.parametrize("storage", ["ros1", "sqlite3", "mcap"])
def test_bag_joint_states(tmp_path: Path, storage: str) -> None:
    rng = np.random.default_rng(4)
    msgs, stamps, q = _arm_messages(rng, 30)
    # a commanded topic at other instants, linear in time, so interpolation is exact
    slope, offset = rng.uniform(-1, 1, 6), rng.uniform(-1, 1, 6)
    cmd_ns = T0 - 5_000_000 + np.arange(40) * 3_000_000
    for n in cmd_ns:
        t = (n - T0) / 1e9
        msgs.append(("/joint_command", int(n), int(n), ARM[::-1], list((offset + slope * t)[::-1])))
    msgs.sort(key=lambda m: m[1])
    path = _write_bag(_bag_path(tmp_path, storage), storage, msgs)
    if storage == "sqlite3":
        path = path / f"{path.name}.db3"  # the storage file alone works too
    log = read_joint_log(path, joint_names=ARM)
    np.testing.assert_allclose(log.time, _ns_to_s(stamps), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(log.joints, q)
    assert log.names == tuple(ARM)
    expected_cmd = offset + slope * ((stamps - T0) / 1e9)[:, None]
    np.testing.assert_allclose(log.commanded, expected_cmd, atol=1e-9)
    fmt = "ros1" if storage == "ros1" else "ros2"
    assert log.source.startswith(f"{fmt} bag, topic /joint_states, header stamps")
    assert "commanded: /joint_command" in log.source

    sub = read_joint_log(path, joint_names=["joint_3", "joint_1"])
    assert sub.names == ("joint_3", "joint_1")
    np.testing.assert_array_equal(sub.joints, q[:, [2, 0]])
    np.testing.assert_allclose(sub.commanded, expected_cmd[:, [2, 0]], atol=1e-9)

    # default order: the first message's, gripper included; the command topic lacks it
    full = read_joint_log(path)
    first = next(m for m in msgs if m[0] == "/joint_states")
    assert full.names == tuple(first[3]) and full.commanded is None
    assert "commanded topic /joint_command not used: " in full.source
    assert "lacks joint 'gripper_finger_joint'" in full.source


def test_bag_first_message_names_and_gripper(tmp_path: Path) -> None:
    """Default joint order: the first message's, gripper included."""
    rng = np.random.default_rng(5)
    msgs, stamps, q = _arm_messages(rng, 5)
    path = _write_bag(_bag_path(tmp_path, "mcap"), "mcap", msgs)
    log = read_joint_log(path)
    assert log.names == tuple(msgs[0][3])
    lookup = dict(zip([*ARM, "gripper_finger_joint"], range(7)))
    full = np.concatenate([q, np.full((5, 1), 0.04)], axis=1)
    np.testing.assert_array_equal(log.joints, full[:, [lookup[n] for n in log.names]])
    assert log.commanded is None


def test_bag_zero_stamps_use_receive_time(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    msgs, stamps, q = _arm_messages(rng, 8, zero_stamps=True)
    path = _write_bag(_bag_path(tmp_path, "ros1"), "ros1", msgs)
    log = read_joint_log(path, joint_names=ARM)
    np.testing.assert_allclose(log.time, _ns_to_s(stamps + 1_500_000), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(log.joints, q)
    assert "receive time (header stamps are all zero)" in log.source


def test_bag_unordered_and_repeated_messages(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    msgs, stamps, q = _arm_messages(rng, 10)
    msgs[3], msgs[4] = (
        (msgs[3][0], msgs[4][1], *msgs[3][2:]),
        (msgs[4][0], msgs[3][1], *msgs[4][2:]),
    )
    msgs.insert(6, (msgs[6][0], msgs[6][1], *msgs[5][2:]))  # an exact repeat of message 6
    path = _write_bag(_bag_path(tmp_path, "sqlite3"), "sqlite3", msgs)
    log = read_joint_log(path, joint_names=ARM)
    np.testing.assert_allclose(log.time, _ns_to_s(stamps), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(log.joints, q)
    assert "sorted 2 messages by time" in log.source
    assert "dropped 1 repeated messages" in log.source


# ---------------------------------------------------------------- bad input


def _csv(tmp_path: Path, text: str, name: str = "log.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


RTDE_HEAD = "timestamp " + " ".join(f"actual_q_{i}" for i in range(6))
MAP = {"time": "t", "joints": ["a", "b"]}


@pytest.mark.parametrize(
    ("text", "mapping", "message"),
    [
        (
            " ".join(f"actual_q_{i}" for i in range(6)) + "\n" + "0 " * 6 + "\n" + "1 " * 6,
            None,
            r"no 'timestamp' column",
        ),
        (
            "timestamp actual_q_0 actual_q_1 actual_q_2 actual_q_5\n0 0 0 0 0\n1 0 0 0 0\n",
            None,
            r"no joint column 'actual_q_3', 'actual_q_4'",
        ),
        (
            RTDE_HEAD + "\n0 0 0 0 0 0 0\n1 0 0 x 0 0 0\n",
            None,
            r"line 3, column 'actual_q_2': 'x' is not a number",
        ),
        (RTDE_HEAD + "\n0 0 0 0 0 0 0\n1 0 0 0 0 0\n", None, r"line 3 has 6 fields"),
        (
            RTDE_HEAD + "\n0 0 0 0 0 0 0\n1 0 0 nan 0 0 0\n",
            None,
            r"line 3, column 'actual_q_2': nan is not a finite number",
        ),
        (RTDE_HEAD + "\n0 0 0 0 0 0 0\n", None, r"1 data rows; a joint log needs at least 2"),
        (
            RTDE_HEAD + "\n0 0 0 0 0 0 0\n2 0 0 0 0 0 0\n1 0 0 0 0 0 0\n",
            None,
            r"time goes back at line 4 \(1.0 s after 2.0 s\)",
        ),
        (
            RTDE_HEAD + "\n0 0 0 0 0 0 0\n0 1 0 0 0 0 0\n",
            None,
            r"line 3 repeats the time 0.0 s of line 2 with other joint values",
        ),
        (
            RTDE_HEAD + "\n0 0 0 0 0 0 0\n0 0 0 0 0 0 0\n",
            None,
            r"1 distinct sample\(s\); a joint log needs at least 2",
        ),
        ("x,a,b\n0,1,2\n1,1,2\n", MAP, r"no time column 't' \(columns: x, a, b\)"),
        ("t,a\n0,1\n1,1\n", MAP, r"no joint column 'b'"),
        ("t,a,b\n0,1,2\n1,1,2\n", {"joints": ["a", "b"]}, r"lacks the key 'time'"),
        ("t,a,b\n0,1,2\n1,1,2\n", {"time": "t"}, r"lacks the key 'joints'"),
        ("t,a,b\n0,1,2\n1,1,2\n", {**MAP, "delimeter": ";"}, r"unknown key 'delimeter'"),
        ("t,a,b\n0,1,2\n1,1,2\n", {**MAP, "unit": "grad"}, r"unit 'grad' is not one of"),
        ("t,a,b\n0,1,2\n1,1,2\n", {**MAP, "commanded": ["a"]}, r"'commanded' has 1 entries"),
        (
            "t,a,b\nnoon,1,2\n1,1,2\n",
            {**MAP, "time_format": "iso8601"},
            r"line 2: 'noon' is not an ISO 8601 time",
        ),
        ("t,a,b\n0,1,2\n1,1,2\n", None, r"give a column mapping"),
    ],
)
def test_bad_csv(tmp_path: Path, text: str, mapping: dict | None, message: str) -> None:
    path = _csv(tmp_path, text)
    with pytest.raises(UserError, match=message) as info:
        read_joint_log(path, mapping=mapping)
    assert "\n" not in str(info.value)


def test_repeated_rows_dropped(tmp_path: Path) -> None:
    path = _csv(tmp_path, RTDE_HEAD + "\n0 0 0 0 0 0 0\n0 0 0 0 0 0 0\n1 1 1 1 1 1 1\n")
    log = read_joint_log(path)
    np.testing.assert_array_equal(log.time, [0.0, 1.0])
    assert log.source == "ur-rtde; dropped 1 repeated lines (same time and values)"


def test_bad_mapping_file(tmp_path: Path) -> None:
    path = _csv(tmp_path, "t,a,b\n0,1,2\n1,1,2\n")
    bad = _csv(tmp_path, "{time: t", "map.json")
    with pytest.raises(UserError, match=r"map.json: not a readable JSON mapping"):
        read_joint_log(path, mapping=bad)
    with pytest.raises(UserError, match=r"no such file"):
        read_joint_log(tmp_path / "missing.csv", mapping=MAP)
    with pytest.raises(UserError, match=r"a topic applies to ROS bags"):
        read_joint_log(path, mapping=MAP, topic="/joint_states")


def test_bad_bags(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    msgs, _, _ = _arm_messages(rng, 4)
    only_text = _write_bag(
        tmp_path / "text.bag", "ros1", [("/chatter", 1, "hi"), ("/chatter", 2, "x")]
    )
    with pytest.raises(UserError, match=r"no sensor_msgs/JointState topic \(topics: /chatter"):
        read_joint_log(only_text)

    two = msgs + [
        (m[0].replace("joint_states", "left/joint_states"), m[1] + 1, *m[2:]) for m in msgs
    ]
    two.sort(key=lambda m: m[1])
    path = _write_bag(tmp_path / "two", "mcap", two)
    with pytest.raises(
        UserError, match=r"several JointState topics \(/joint_states, /left/joint_states\)"
    ):
        read_joint_log(path)
    assert read_joint_log(path, topic="/left/joint_states").joints.shape == (4, 7)
    with pytest.raises(UserError, match=r"no JointState topic '/right'"):
        read_joint_log(path, topic="/right")
    with pytest.raises(UserError, match=r"joint 'elbow'"):
        read_joint_log(path, topic="/joint_states", joint_names=["joint_1", "elbow"])

    one = _write_bag(tmp_path / "one.bag", "ros1", msgs[:1])
    with pytest.raises(UserError, match=r"1 distinct sample\(s\)"):
        read_joint_log(one)
    partial = msgs[:2] + [(msgs[2][0], msgs[2][1], 0, *msgs[2][3:])] + msgs[3:]
    path = _write_bag(tmp_path / "partial.bag", "ros1", partial)
    with pytest.raises(
        UserError, match=r"1 of 4 messages on /joint_states have a zero header stamp"
    ):
        read_joint_log(path)
    with pytest.raises(UserError, match=r"a folder but not a ROS 2 bag"):
        read_joint_log(tmp_path)
