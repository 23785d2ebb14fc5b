"""Pose-CSV importer against the real UR10 + laser-tracker series in shared/data/ipa-robot-accuracy.

The measured Euler convention is checked physically: with the right convention one
rigid tracker<-base and one flange<-probe transform explain all measured probe poses
(4 virtual points per pose) to about a millimetre through nominal UR10 kinematics;
with a wrong convention the same fit is off by centimetres.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from robtraj import UserError, read_recording, write_recording
from robtraj.importers import import_file, import_pose_csv, load_pose_series
from robtraj.importers._pose_csv import import_pose_folder

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ipa-robot-accuracy"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="shared data not present")
GRID = DATA / "Series_A" / "measurements_grid.csv"
JOINTS = DATA / "Series_B" / "measurements_joint_configurations.csv"
HANDEYE = DATA / "Series_B" / "calibration_handeye.csv"

UR10_D = np.array([0.1273, 0, 0, 0.163941, 0.1157, 0.0922])
UR10_A = np.array([0, -0.612, -0.5723, 0, 0, 0])
UR10_ALPHA = np.array([np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0])
POINTS = np.vstack([np.zeros(3), 0.1 * np.eye(3)])


def ur10_fk(q: np.ndarray) -> np.ndarray:
    """Nominal standard-DH UR10 base<-flange, `(N, 4, 4)`."""
    T = np.tile(np.eye(4), (q.shape[0], 1, 1))
    for i in range(6):
        ct, st = np.cos(q[:, i]), np.sin(q[:, i])
        ca, sa = np.cos(UR10_ALPHA[i]), np.sin(UR10_ALPHA[i])
        A = np.zeros_like(T)
        A[:, 0] = np.stack([ct, -st * ca, st * sa, UR10_A[i] * ct], -1)
        A[:, 1] = np.stack([st, ct * ca, -ct * sa, UR10_A[i] * st], -1)
        A[:, 2, 1:] = [sa, ca, UR10_D[i]]
        A[:, 3, 3] = 1
        T = T @ A
    return T


def _procrustes(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt


def _axis_rotations() -> list[np.ndarray]:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product([1, -1], repeat=3):
            r = np.eye(3)[list(perm)] * np.array(signs)[:, None]
            if np.linalg.det(r) > 0:
                out.append(r)
    return out


def rigid_fit_errors(fk: np.ndarray, meas: np.ndarray) -> np.ndarray:
    """Fit meas = X . fk . Y; per-pose, per-virtual-point position errors `(N, 4)` [m]."""
    ra, rm = fk[:, :3, :3], meas[:, :3, :3]
    best = None
    for ry in _axis_rotations():  # rotation init: alternating Procrustes from 24 starts
        for _ in range(30):
            rx = _procrustes(np.einsum("nij,nkj->ik", rm, ra @ ry))
            ry = _procrustes(np.einsum("nji,njk->ik", rx @ ra, rm))
        cost = np.sum((rx @ ra @ ry - rm) ** 2)
        if best is None or cost < best[0]:
            best = (cost, rx, ry)
    _, rx, ry = best
    # translations are then linear: p_m = rx ra t_y + rx p_a + t_x
    n = fk.shape[0]
    lhs = np.concatenate([rx @ ra, np.tile(np.eye(3), (n, 1, 1))], axis=2).reshape(3 * n, 6)
    rhs = (meas[:, :3, 3] - fk[:, :3, 3] @ rx.T).reshape(-1)
    t = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    target = meas[:, None, :3, 3] + np.einsum("nij,kj->nki", rm, POINTS)

    def residual(p):
        X, Y = Rotation.from_rotvec(p[:3]).as_matrix(), Rotation.from_rotvec(p[6:9]).as_matrix()
        in_flange = POINTS @ Y.T + p[9:12]
        world = np.einsum("nij,kj->nki", ra, in_flange) + fk[:, None, :3, 3]
        return (world @ X.T + p[3:6] - target).ravel()

    p0 = np.concatenate(
        [Rotation.from_matrix(rx).as_rotvec(), t[3:], Rotation.from_matrix(ry).as_rotvec(), t[:3]]
    )
    sol = least_squares(residual, p0, method="lm")
    return np.linalg.norm(sol.fun.reshape(n, 4, 3), axis=-1)


def _measured(path: Path, euler: str, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Nominal UR10 FK of the joints and the measured poses read with `euler`."""
    from robtraj.importers import PRESETS

    measured = {**PRESETS["ipa-ur10"]["measured"], "euler": euler}
    joints, meas, *_ = load_pose_series(path, mapping={"measured": measured})
    return ur10_fk(joints[::step]), meas[::step]


@pytest.mark.parametrize("path,step", [(GRID, 10), (JOINTS, 1)], ids=["Series_A", "Series_B"])
def test_stated_euler_convention_fits_rigidly(path, step, capsys):
    """README: measured rotation is intrinsic XYZ in degrees; wrong conventions fit badly."""
    results = {}
    for euler in ["XYZ", "xyz", "ZYX", "zyx"]:
        fk, meas = _measured(path, euler, step)
        err = rigid_fit_errors(fk, meas) * 1e3
        results[euler] = (float(err.mean()), float(err.max()))
    with capsys.disabled():
        print(f"\n{path.parent.name}: rigid-fit error mean/max [mm]", results)
    right_mean, right_max = results["XYZ"]
    assert right_mean < 1.5 and right_max < 4.0
    for euler in ["xyz", "ZYX", "zyx"]:
        assert results[euler][0] > 4 * right_mean and results[euler][0] > 5.0


def test_series_b_import(tmp_path):
    rec = import_pose_csv(JOINTS, preset="ipa-ur10")
    n = 1495
    assert rec.n_frames == n and list(rec.led_ids) == [1, 2, 3, 4]
    assert rec.attrs["source"] == "import"
    # first data row: 383,76294; -3240,8734; 201,93157 mm; -90,179302; -20,118749; -90,169308 deg
    np.testing.assert_allclose(rec.positions[0, 0], [0.38376294, -3.2408734, 0.20193157])
    rot = Rotation.from_euler("XYZ", [-90.179302, -20.118749, -90.169308], degrees=True)
    np.testing.assert_allclose(
        rec.positions[0, 1] - rec.positions[0, 0], 0.1 * rot.as_matrix()[:, 0]
    )
    np.testing.assert_allclose(rec.tool.constellation, np.vstack([np.zeros(3), 0.1 * np.eye(3)]))
    assert list(rec.tool.reference_leds) == [1, 2, 3]
    np.testing.assert_allclose(rec.probe.tool_pose.position, rec.positions[:, 0])
    assert rec.robot.model == "ur10" and rec.robot.joints.shape == (n, 6)
    np.testing.assert_allclose(
        rec.robot.joints[1], [-0.908775, -0.052173, -1.92746, -1.16213, -2.05921, -0.000837151]
    )
    assert rec.temperature[0] == pytest.approx(21.8675, abs=1e-4)
    np.testing.assert_allclose(rec.program.targets.position[1], [0.4, -0.4, 0.8])
    want = Rotation.from_euler("xyz", [2.96706, 1.5708, 1.5708]).as_matrix()
    got = Rotation.from_quat(np.roll(rec.program.targets.quaternion_wxyz[1], -1)).as_matrix()
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert set(rec.program.motion) == {"joint"} and not rec.program.speed.any()
    std = rec.extras["tracker/pose_std"]
    assert std.shape == (n, 6)
    np.testing.assert_allclose(std[0, :3], [0.031674e-3, 0.013252e-3, 0.0037622e-3])
    np.testing.assert_allclose(std[0, 3:], np.deg2rad([0.0011832, 0.0013871, 0.0041345]))
    assert "tracker/wallclock" not in rec.extras  # spreadsheet-rounded, not usable
    np.testing.assert_allclose(rec.time, np.arange(n))
    back = read_recording(write_recording(rec, tmp_path / "b.h5"))
    np.testing.assert_array_equal(back.extras["tracker/pose_std"], std)
    assert back.robot.model == "ur10" and back.program.motion[0] == "joint"


def test_every_series_in_the_folder():
    recs = import_pose_folder(DATA, preset="ipa-ur10")
    assert sorted(recs) == [
        "Series_A/measurements_grid.csv",
        "Series_B/calibration_handeye.csv",
        "Series_B/measurements_joint_configurations.csv",
    ]
    grid = recs["Series_A/measurements_grid.csv"]
    assert grid.n_frames == 11911 and grid.robot.joints.shape == (11911, 6)
    wall = grid.extras["tracker/wallclock"]
    assert wall.shape == (11911,) and wall[1] - wall[0] == 20.0  # 16:39:04 -> 16:39:24
    handeye = recs["Series_B/calibration_handeye.csv"]
    assert handeye.n_frames == 25 and handeye.robot is None and handeye.temperature is None
    q = handeye.program.targets.quaternion_wxyz[0]
    want = np.array([0.464994502, -0.271078827, 0.60327616, -0.588518698])
    np.testing.assert_allclose(q, want / np.linalg.norm(want), atol=1e-9)
    for rec in recs.values():
        assert np.all(np.isfinite(rec.positions))


def test_load_pose_series_shapes():
    joints, meas, cmd, temp, std = load_pose_series(HANDEYE)
    assert joints is None and temp is None and std is None
    assert meas.shape == (25, 4, 4) and cmd.shape == (25, 4, 4)
    np.testing.assert_allclose(meas[0, :3, 3], [0.26490982, -2.9849658, 0.00040478541])
    np.testing.assert_allclose(meas[:, 3], np.tile([0, 0, 0, 1.0], (25, 1)))


def test_mapping_file_and_errors(tmp_path):
    csv = tmp_path / "p.csv"
    csv.write_text("t,x,y,z,a,b,c\n0,1000,0,0,0,0,90\n1,0,2000,0,90,0,0\n")
    mapping = tmp_path / "m.json"
    mapping.write_text(
        json.dumps(
            {
                "measured": {
                    "position": ["x", "y", "z"],
                    "position_unit": "mm",
                    "rotation": ["a", "b", "c"],
                    "angle_unit": "deg",
                    "euler": "XYZ",
                }
            }
        )
    )
    rec = import_file(csv, mapping=mapping, rate=10.0)
    np.testing.assert_allclose(rec.time, [0, 0.1])
    np.testing.assert_allclose(
        rec.positions[0], [[1, 0, 0], [1, 0.1, 0], [0.9, 0, 0], [1, 0, 0.1]], atol=1e-12
    )
    assert rec.robot is None and rec.program is None
    with pytest.raises(UserError, match="needs a column mapping"):
        import_pose_csv(csv)
    with pytest.raises(UserError, match="unknown preset"):
        import_pose_csv(csv, preset="nope")
    with pytest.raises(UserError, match="measured column 'measurement_x' not found"):
        import_pose_csv(csv, preset="ipa-ur10")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y,z,a,b,c\n0,1000,0,0,0,0,90\n1,zz,2000,0,90,0,0\n")
    with pytest.raises(UserError, match=r"row 3, column 'x': 'zz' is not a number"):
        import_pose_csv(bad, mapping=mapping)
    with pytest.raises(UserError, match="Euler sequence"):
        import_pose_csv(
            csv,
            mapping={
                "measured": {
                    "position": ["x", "y", "z"],
                    "rotation": ["a", "b", "c"],
                    "euler": "XyZ",
                }
            },
        )
