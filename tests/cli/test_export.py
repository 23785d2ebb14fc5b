"""`robtraj export`: the calibrated robot as URDF (against yourdfpy's forward kinematics
of the file, and against robtraj's kinematics with the effects applied), and every
parameter with its σ as JSON."""

import json

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
import yourdfpy
from cli_helpers import assert_one_line_error, run_cli

from robtraj.analysis.export import calibration_urdf, not_representable, parameter_document
from robtraj.calibration_file import load_calibration
from robtraj.estimate.calibration import CalibrationResult
from robtraj.importers import read_robot_model
from robtraj.model import (
    Effects,
    abb_irb2400_16,
    dh_corrections,
    forward_kinematics,
    robot_from_log,
    ur10,
)
from robtraj.recording import write_recording
from robtraj.sim import simulate


def _calibration(robot, rng, tilt: bool = True) -> CalibrationResult:
    """A calibration with random geometric errors of realistic size and a compliance."""
    j = robot.n_joints
    twist = rng.normal(scale=2e-4, size=(j, 2))
    if not tilt:
        twist[:, 1] = 0.0
    effects = {
        "joint_offset": rng.normal(scale=1e-3, size=j),
        "link_length": rng.normal(scale=3e-4, size=(j, 2)),
        "link_twist": twist,
        "joint_compliance": np.full(j, 1e-6),
    }
    q = rng.normal(size=4)
    doc = {
        "camera_from_base": {"position": [3.0, 0.1, 1.0], "quaternion_wxyz": [1, 0, 0, 0]},
        "flange_from_tool": {
            "position": rng.normal(scale=0.05, size=3).tolist(),
            "quaternion_wxyz": (q / np.linalg.norm(q)).tolist(),
        },
        "constellation": {"led_ids": [1, 2, 3], "positions": np.eye(3).tolist()},
        "effects": {k: v.tolist() for k, v in effects.items()},
        "estimated": list(effects),
    }
    return CalibrationResult.from_json(doc)


def _model_fk(robot, calib, q):
    """base←tool of the calibrated geometry the way the measurement model computes it:
    the effects as DH corrections and joint offsets, not a rewritten table."""
    eff = Effects.from_dict(calib.effects, robot.n_joints)
    dh_delta, tilt = dh_corrections(robot, eff)
    fft = calib.flange_from_tool
    tool = jaxlie.SE3(
        jnp.concatenate([jnp.asarray(fft.quaternion_wxyz), jnp.asarray(fft.position)])
    )
    return jax.vmap(
        lambda qq: (
            forward_kinematics(robot, qq + eff.joint_offset, dh_delta, tilt) @ tool
        ).as_matrix()
    )(q)


@pytest.mark.parametrize("make", [abb_irb2400_16, ur10])
def test_urdf_holds_the_calibrated_geometry(tmp_path, make):
    robot, rng = make(), np.random.default_rng(7)
    calib = _calibration(robot, rng)
    path = tmp_path / "calibrated.urdf"
    path.write_text(calibration_urdf(calib, robot))
    urdf = yourdfpy.URDF.load(path, load_meshes=False, build_collision_scene_graph=False)
    q = rng.uniform(-np.pi, np.pi, (1000, robot.n_joints))
    want = np.asarray(_model_fk(robot, calib, jnp.asarray(q)))
    names = [j.name for j in urdf.robot.joints if j.type == "revolute"]
    worst = 0.0
    for qq, w in zip(q, want, strict=True):
        urdf.update_cfg(dict(zip(names, qq, strict=True)))
        got = urdf.get_transform("tool", "base_link")
        worst = max(
            worst, np.abs(got[:3, 3] - w[:3, 3]).max(), np.abs(got[:3, :3] - w[:3, :3]).max()
        )
    assert worst < 1e-9
    assert "joint_compliance" in path.read_text()  # listed as not representable
    assert not_representable(calib) == ["joint_compliance (not geometry)"]


def test_urdf_reads_back_through_the_campaign_path(tmp_path):
    """Without tilts of parallel axes (which standard DH cannot hold), `read_robot_model`
    gives the calibrated flange kinematics back to 1e-9 m."""
    robot, rng = abb_irb2400_16(), np.random.default_rng(3)
    calib = _calibration(robot, rng, tilt=False)
    path = tmp_path / "calibrated.urdf"
    path.write_text(calibration_urdf(calib, robot))
    desc = read_robot_model(path)
    back = robot_from_log(desc.robot_log(np.zeros(0), np.zeros((0, 6))))
    q = jnp.asarray(rng.uniform(-np.pi, np.pi, (1000, 6)))
    eff = Effects.from_dict(calib.effects, 6)
    dh_delta, tilt = dh_corrections(robot, eff)
    want = jax.vmap(
        lambda qq: forward_kinematics(robot, qq + eff.joint_offset, dh_delta, tilt).as_matrix()
    )(q)
    got = jax.vmap(lambda qq: forward_kinematics(back, qq).as_matrix())(q)
    assert float(jnp.abs(got - want).max()) < 1e-9


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    rec = simulate("calibration", seed=4, duration=20.0, rate=100.0, effects={"link_length": 2e-4})
    write_recording(rec.replace(truth=None), tmp / "rec.h5")
    from robtraj.cli import main

    assert main(["calibrate", str(tmp / "rec.h5"), "-o", str(tmp / "c.json"),
                 "--estimate", "link_length"]) == 0  # fmt: skip
    return tmp


def test_json_holds_every_parameter_with_its_sigma(fitted):
    calib = load_calibration(fitted / "c.json")
    doc = json.loads(json.dumps(parameter_document(calib)))
    sigma = calib.sigma
    ll = doc["effects"]["link_length"]
    sig = np.ravel(np.array(ll["sigma"], dtype=object))
    for name, value, s in zip(ll["components"], np.ravel(ll["value"]), sig, strict=True):
        want = sigma.get(name, 0.0)
        assert s == (want if np.isfinite(want) else None), name
        assert (
            value == np.asarray(calib.effects["link_length"])[int(name[12]), "da".index(name[-1])]
        )
    assert doc["camera_from_base"]["sigma"]["tx"] == sigma["camera_from_base.tx"]
    led = doc["constellation"]["led_ids"][0]
    assert doc["constellation"]["sigma"][0][2] == sigma[f"constellation[LED {led}].z"]
    assert doc["robot"] == {"model": "abb_irb2400_16"}


def test_cli_export_and_its_errors(capsys, fitted):
    code, out, err = run_cli(
        capsys, "export", fitted / "c.json", "--format", "urdf", "-o", fitted / "r.urdf"
    )
    assert code == 0, err
    assert yourdfpy.URDF.load(fitted / "r.urdf", load_meshes=False).link_map["tool"] is not None
    code, _, err = run_cli(
        capsys, "export", fitted / "c.json", "--format", "urdf", "-o", fitted / "r.urdf"
    )
    assert_one_line_error(code, err, "exists")
    old = json.loads((fitted / "c.json").read_text())
    old.pop("robot")
    (fitted / "old.json").write_text(json.dumps(old))
    code, _, err = run_cli(
        capsys, "export", fitted / "old.json", "--format", "urdf", "-o", fitted / "o.urdf"
    )
    assert_one_line_error(code, err, "does not name its robot")
    code, _, err = run_cli(capsys, "export", fitted / "old.json", "--format", "urdf", "-o", fitted / "o.urdf",
                           "--robot", "ur10")  # fmt: skip
    assert code == 0, err
