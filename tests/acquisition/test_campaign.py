"""A measurement campaign end to end through the CLI: the tracker stream recorded from the
emulator, the joint log on the controller's clock (UR RTDE CSV and a ROS 2 bag, 7.3 s off
on the UNIX epoch), the robot as URDF, the tool as JSON, the program as CSV; `attach`
joins them and `calibrate` on the result agrees with the calibration of the simulated
file itself. (The simulated robot is the IRB2400: the RTDE file is a format, here it
carries the ABB's joints.)"""

import json
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from acq_helpers import popen, wait_for_file
from test_cli_acquisition import _finish, _reap

from robtraj import read_recording, write_recording
from robtraj.calibration_file import load_calibration
from robtraj.jax_ops import rotation_angle
from robtraj.sim import CONTROLLER_EPOCH, simulate, write_campaign

#: the IRB2400 as URDF in the ROS-Industrial style, written from the data sheet
URDF = Path(__file__).resolve().parents[1] / "importers" / "data" / "abb_irb2400.urdf"

#: [s] the simulated robot's own clock offset τ, and the controller clock's shift
TAU, SHIFT = 0.004, 7.3
#: the URDF's joint names (the bag lists them in another order, with a gripper)
JOINT_NAMES = [f"joint_{k + 1}" for k in range(6)]


def _cli(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    out = subprocess.run(
        [sys.executable, "-m", "robtraj", *args], capture_output=True, text=True, timeout=600
    )
    if check:
        assert out.returncode == 0, out.stderr
    return out


def _record_from_emulator(src, out, tmp_path):
    emu = popen(
        "emulate", str(src), "--port", "socket://127.0.0.1:0", "--rate", "0",
        "--port-file", str(tmp_path / "port"),
    )  # fmt: skip
    try:
        url = wait_for_file(tmp_path / "port", proc=emu)
        rec = popen("record", "--port", url, "-o", str(out))
        code, _, err = _finish(rec, timeout=120)
        assert code == 0, err
        assert _finish(emu)[0] == 0
    finally:
        _reap(emu)


def _write_ros2_bag(path, time_s: np.ndarray, joints: np.ndarray) -> None:
    """A ROS 2 bag of sensor_msgs/JointState with the joints shuffled and a gripper."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    js, header, stamp = (
        store.types["sensor_msgs/msg/JointState"],
        store.types["std_msgs/msg/Header"],
        store.types["builtin_interfaces/msg/Time"],
    )
    order = [3, 0, 5, 1, 4, 2]
    ns = (
        np.round((time_s - CONTROLLER_EPOCH) * 1e9).astype(np.int64) + int(CONTROLLER_EPOCH) * 10**9
    )
    with Writer(path, version=8) as writer:
        conn = writer.add_connection("/joint_states", js.__msgtype__, typestore=store)
        for t, q in zip(ns, joints, strict=True):
            msg = js(
                header=header(
                    stamp=stamp(sec=int(t // 10**9), nanosec=int(t % 10**9)), frame_id=""
                ),
                name=[JOINT_NAMES[k] for k in order] + ["gripper"],
                position=np.array([*q[order], 0.01]),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            )
            writer.write(conn, int(t), store.serialize_cdr(msg, js.__msgtype__))


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("campaign")
    sim = simulate("calibration", seed=3, duration=16.0, rate=250.0, effects={"time_offset": TAU})
    write_recording(sim.replace(truth=None), tmp / "original.h5")
    (tmp / "parts").mkdir()
    files = write_campaign(sim, tmp / "parts", clock_offset=SHIFT, log_format="ur-rtde")
    _record_from_emulator(files.tracker, tmp / "stream.h5", tmp)
    _write_ros2_bag(tmp / "joints_bag", sim.robot.time + CONTROLLER_EPOCH + SHIFT, sim.robot.joints)
    return tmp, files, sim


@pytest.mark.parametrize("log", ["ur-rtde", "ros2"])
def test_attach_then_calibrate_agrees_with_the_original(campaign, log):
    tmp, files, sim = campaign
    run = tmp / f"run_{log}.h5"
    log_args = (
        ["--robot-log", str(files.robot_log)]
        if log == "ur-rtde"
        else ["--robot-log", str(tmp / "joints_bag")]  # joint order: the URDF's names
    )
    out = _cli(
        "attach", str(tmp / "stream.h5"), "-o", str(run), *log_args, "--robot", str(URDF),
        "--tool", str(files.tool), "--program", str(files.program), "--json",
        str(tmp / f"attach_{log}.json"),
    )  # fmt: skip
    assert "robot clock = tracker clock +" in out.stdout
    doc = json.loads((tmp / f"attach_{log}.json").read_text())
    # the log's clock runs CONTROLLER_EPOCH + SHIFT + τ ahead of the tracker's
    assert files.clock_offset == CONTROLLER_EPOCH + SHIFT + TAU
    assert abs(doc["clock"]["offset_s"] - files.clock_offset) < 2e-3

    rec = read_recording(run)
    assert rec.robot.clock_offset == pytest.approx(doc["clock"]["offset_s"], abs=0)
    np.testing.assert_allclose(rec.program.targets.position, sim.program.targets.position)

    calib = {}
    for name, path in (("original", tmp / "original.h5"), (log, run)):
        target = tmp / f"calib_{name}.json"
        if not target.exists():
            _cli("calibrate", str(path), "-o", str(target), "--estimate", "time_offset")
        calib[name] = load_calibration(target)
    a, b = calib["original"], calib[log]
    assert "time_offset" in b.estimated  # estimated by default after a clock alignment
    for frame in ("camera_from_base", "flange_from_tool"):
        pa, pb = getattr(a, frame).position, getattr(b, frame).position
        sig = np.hypot(*([s[f"{frame}.t{c}"] for c in "xyz"] for s in (a.sigma, b.sigma)))
        assert np.all(np.abs(pa - pb) < 2 * sig), (frame, pa - pb, sig)
        angle = rotation_angle(
            jnp.asarray(getattr(a, frame).quaternion_wxyz),
            jnp.asarray(getattr(b, frame).quaternion_wxyz),
        )
        sig_r = max(np.hypot(a.sigma[f"{frame}.r{c}"], b.sigma[f"{frame}.r{c}"]) for c in "xyz")
        assert float(angle) < 2 * np.sqrt(3) * sig_r
    # τ of the original is the robot's whole offset; the attached one is what is left
    # after the alignment (the log's clock is SHIFT ahead on another epoch)
    tau_b = b.time_offset + (rec.robot.clock_offset - (CONTROLLER_EPOCH + SHIFT))
    assert abs(a.time_offset - tau_b) < 2 * np.hypot(a.sigma["time_offset"], b.sigma["time_offset"])
