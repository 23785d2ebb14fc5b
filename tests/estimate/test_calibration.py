"""Bundle calibration: coverage against simulation truth, closed form vs OpenCV, clock
offset, identifiability, robust loss, bad input, JSON."""

import dataclasses
import json

import cv2
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from robtraj import UserError
from robtraj.estimate._calib_data import prepare
from robtraj.estimate._calib_init import pose_pairs
from robtraj.estimate.calibration import (
    CalibrationResult,
    align_to_gauge,
    error_against,
    fit,
    robot_world_hand_eye,
)
from robtraj.model import EFFECT_NAMES, MOTION_THRESHOLD, Effects
from robtraj.recording import Pose
from robtraj.sim import simulate

SEEDS = range(20)
DURATION, RATE = 16.0, 25.0  # 6 static poses, 400 frames: cheap, one compilation


def _se3(pose: Pose) -> jaxlie.SE3:
    return jaxlie.SE3(
        jnp.concatenate([jnp.asarray(pose.quaternion_wxyz), jnp.asarray(pose.position)])
    )


def _tangent_error(est: Pose, truth: Pose) -> np.ndarray:
    """log(truth⁻¹ · est): the error in the tangent space of the true pose."""
    return np.asarray((_se3(truth).inverse() @ _se3(est)).log())


def _normalised_errors(res: CalibrationResult, rec) -> np.ndarray:
    sigma = np.sqrt(np.diag(res.covariance))
    err = error_against(res, rec.truth, rec.tool.led_ids)
    ok = sigma > 0  # LEDs never seen are not estimated
    return err[ok] / sigma[ok]


@pytest.fixture(scope="module")
def fits():
    out = []
    for seed in SEEDS:
        rec = simulate("calibration", seed=seed, duration=DURATION, rate=RATE)
        out.append((rec, fit(rec)))
    return out


def test_estimates_cover_truth_within_reported_covariance(fits):
    z = np.concatenate([_normalised_errors(res, rec) for rec, res in fits])
    rms = np.sqrt(np.mean(z**2))
    assert 1 / 1.5 < rms < 1.5, rms
    assert np.mean(np.abs(z) < 3) > 0.98
    for _, res in fits:
        assert res.converged
        assert res.gauge == "reference_constellation"
        assert res.identifiability["dropped"] == []
        # the noise model brings the weighted residuals to unit variance
        assert 0.8 < res.chi2 / (res.n_residuals - res.n_params) < 1.25


def _pose(wxyz_xyz):
    return Pose(position=wxyz_xyz[4:], quaternion_wxyz=wxyz_xyz[:4])


def test_from_closed_form_and_from_truth_reach_the_same_optimum(fits):
    for rec, res in fits[:5]:
        p_true, fft_true = align_to_gauge(
            res, rec.truth.constellation, rec.truth.flange_from_tool, led_ids=rec.tool.led_ids
        )
        start = dataclasses.replace(
            res,
            camera_from_base=rec.truth.camera_from_base,
            flange_from_tool=fft_true,
            constellation=p_true,
        )
        again = fit(rec, init=start)
        sigma = np.sqrt(np.diag(res.covariance))
        d = np.concatenate(
            [
                _tangent_error(again.camera_from_base, res.camera_from_base),
                _tangent_error(again.flange_from_tool, res.flange_from_tool),
                (again.constellation - res.constellation).reshape(-1),
            ]
        )
        ok = sigma > 0
        assert np.max(np.abs(d[ok] / sigma[ok])) < 1e-2


def test_one_gauss_newton_step_from_the_whole_fit_is_the_fit_to_half_of_it(fits):
    """The held-out fits' premise: from the optimum on every frame, one Gauss–Newton
    step on alternate time blocks reaches their optimum within the solver's own
    tolerance (1e-2 σ, as two solves of one optimum above), where the blocks move it by
    about a σ."""
    for rec, res in fits[:3]:
        train = np.where((np.arange(rec.n_frames) * 8 // rec.n_frames % 2 == 0)[:, None],
                         res.weights, 0.0)  # fmt: skip
        step = fit(rec, init=res, weights=train, one_step=True, robust_sigma=False)
        solved = fit(rec, init=res, weights=train, robust_sigma=False)
        assert step.convergence == "one Gauss–Newton step"

        def params(r):
            return np.concatenate(
                [
                    _tangent_error(r.camera_from_base, res.camera_from_base),
                    _tangent_error(r.flange_from_tool, res.flange_from_tool),
                    (r.constellation - res.constellation).reshape(-1),
                ]
            )

        sigma = np.sqrt(np.diag(solved.covariance))
        ok = sigma > 0
        moved = np.abs(params(solved)[ok] / sigma[ok])
        assert np.max(np.abs((params(step) - params(solved))[ok] / sigma[ok])) < 1e-2
        assert np.max(moved) > 0.3  # half the frames do move the optimum


def test_closed_form_agrees_with_opencv_and_refinement_beats_it(fits):
    if not hasattr(cv2, "calibrateRobotWorldHandEye"):  # dropped from OpenCV 5's bindings
        pytest.skip(f"OpenCV {cv2.__version__} has no calibrateRobotWorldHandEye (OpenCV 4.x has)")
    rec, res = fits[0]
    data = prepare(rec)
    cam_from_tool, base_from_flange, n_dwells = pose_pairs(data, Effects.zeros(6), data.reference)
    assert n_dwells >= 6
    z, x = robot_world_hand_eye(cam_from_tool, base_from_flange)

    def rt(wxyz_xyz):
        m = np.asarray(jaxlie.SE3(jnp.asarray(wxyz_xyz)).as_matrix())
        return m[:3, :3], m[:3, 3:]

    # OpenCV: cTw · wTb = cTg · gTb with c = our tool, w = our camera, g = our flange
    tool_from_cam = [rt(np.asarray(_inv(p))) for p in cam_from_tool]
    flange_from_base = [rt(np.asarray(_inv(p))) for p in base_from_flange]
    r_wb, t_wb, r_cg, t_cg = cv2.calibrateRobotWorldHandEye(
        [a[0] for a in tool_from_cam],
        [a[1] for a in tool_from_cam],
        [b[0] for b in flange_from_base],
        [b[1] for b in flange_from_base],
    )
    cv_cfb = np.eye(4)
    cv_cfb[:3, :3], cv_cfb[:3, 3] = r_wb, t_wb[:, 0]
    cv_cfb = jaxlie.SE3.from_matrix(jnp.asarray(cv_cfb))
    ours = jaxlie.SE3(jnp.asarray(z))
    d = np.asarray((cv_cfb.inverse() @ ours).log())
    # same rotation (both Shah's Kronecker null space); the translations solve the same
    # equations arranged in different frames, so they differ at the noise level
    assert np.linalg.norm(d[3:]) < 1e-6 and np.linalg.norm(d[:3]) < 3e-3, d
    tool_from_flange = np.eye(4)
    tool_from_flange[:3, :3], tool_from_flange[:3, 3] = r_cg, t_cg[:, 0]
    cv_fft = jaxlie.SE3.from_matrix(jnp.asarray(tool_from_flange)).inverse()
    d = np.asarray((cv_fft.inverse() @ jaxlie.SE3(jnp.asarray(x))).log())
    assert np.linalg.norm(d[3:]) < 1e-6 and np.linalg.norm(d[:3]) < 3e-3, d

    truth = _se3(rec.truth.camera_from_base)
    err_cv = np.asarray((truth.inverse() @ cv_cfb).log())
    err_fit = _tangent_error(res.camera_from_base, rec.truth.camera_from_base)
    assert np.linalg.norm(err_fit[:3]) < np.linalg.norm(err_cv[:3])
    assert np.linalg.norm(err_fit[3:]) < np.linalg.norm(err_cv[3:])


def test_closed_form_is_close_to_truth(fits):
    """Independent of OpenCV: Shah's closed form lands within a fraction of a millimetre."""
    for rec, res in fits[:5]:
        for key in ("camera_from_base", "flange_from_tool"):
            if key == "flange_from_tool":
                _, truth = align_to_gauge(
                    res, rec.truth.constellation, rec.truth.flange_from_tool, rec.tool.led_ids
                )
            else:
                truth = rec.truth.camera_from_base
            e0 = _tangent_error(res.initial[key], truth)
            e1 = _tangent_error(getattr(res, key), truth)
            assert np.linalg.norm(e0[:3]) < 5e-3 and np.linalg.norm(e0[3:]) < 5e-3, (key, e0)
            assert np.linalg.norm(e1) < np.linalg.norm(e0), key


def _inv(wxyz_xyz):
    return jaxlie.SE3(jnp.asarray(wxyz_xyz)).inverse().wxyz_xyz


def test_clock_offset_recovered_and_confounded_joint_offsets_reported():
    rec = simulate("paper", seed=2, duration=8.0, rate=50.0, effects={"time_offset": 0.003})
    res = fit(rec, estimate=("time_offset", "joint_offset"))
    assert res.converged
    assert abs(res.time_offset - 0.003) < 0.2e-3
    assert abs(res.time_offset - 0.003) < 4 * res.sigma["time_offset"]
    dropped = {d["parameter"]: d["confounded_with"] for d in res.identifiability["dropped"]}
    # joint 1 turns about the base z axis: the same as a camera yaw; joint 6 about the
    # flange z axis: the same as a tool-mount rotation
    assert "joint_offset[0]" in dropped and "camera_from_base.rz" in dropped["joint_offset[0]"]
    assert "joint_offset[5]" in dropped and "flange_from_tool.rz" in dropped["joint_offset[5]"]
    assert res.sigma["joint_offset[0]"] == 0.0
    assert res.sigma["joint_offset[2]"] > 0.0
    doc = res.to_json()
    assert "joint_offset" in doc["effects"] and doc["time_offset"] == res.time_offset
    # the same fit with every other effect of the library in the problem, held at zero
    wide = fit(rec, estimate=("time_offset", "joint_offset"), space=EFFECT_NAMES)
    assert wide.estimated == res.estimated and wide.parameter_names == res.parameter_names
    # (the order of exact null directions is rounding noise)
    assert sorted(map(str, wide.identifiability["dropped"])) == sorted(
        map(str, res.identifiability["dropped"])
    )
    assert abs(wide.time_offset - res.time_offset) < 1e-6 * res.sigma["time_offset"]
    for name, sigma in res.sigma.items():
        assert wide.sigma[name] == pytest.approx(sigma, rel=1e-6, abs=0.0), name
    assert abs(wide.chi2 - res.chi2) < 1e-9 * res.chi2


def test_robust_loss_reports_outlier_frames(fits):
    rec, clean = fits[1]
    pos = rec.positions.copy()
    bad = np.array([40, 41, 200, 300])
    pos[bad] += 3e-3  # a reflection: every LED of these frames off by 3 mm
    dirty = rec.replace(positions=pos)
    res = fit(dirty, robust="cauchy")
    assert set(bad) <= set(res.outlier_frames.tolist())
    e = _tangent_error(res.camera_from_base, clean.camera_from_base)
    s = np.array([res.sigma[f"camera_from_base.{t}"] for t in ("tx", "ty", "tz", "rx", "ry", "rz")])
    assert np.all(np.abs(e) < 3 * s)


def test_the_motion_threshold_is_where_the_velocity_sign_starts(fits):
    """`moving` is the sign of each joint's velocity (central differences of the log,
    held to the frame's log sample) and 0 below the threshold [rad/s], computed here
    directly in numpy."""
    rec, _ = fits[0]
    lt, lj = np.asarray(rec.robot.time), np.asarray(rec.robot.joints)
    v = np.gradient(lj, lt, axis=0)
    moving = {}
    for d in (MOTION_THRESHOLD, 0.05):
        data = prepare(rec, motion_threshold=d)
        k = np.clip(np.searchsorted(lt, data.time, side="right") - 1, 0, lt.size - 1)
        want = np.sign(v[k]) * (np.abs(v[k]) > d)
        np.testing.assert_array_equal(data.moving, want)
        assert data.motion_threshold == d
        moving[d] = np.abs(data.moving).sum()
    # the recording has joint speeds between the two thresholds
    assert moving[0.05] < moving[MOTION_THRESHOLD]


def test_json_round_trip(fits, tmp_path):
    _, res = fits[0]
    doc = json.loads(json.dumps(res.to_json()))
    for key in ["camera_from_base", "flange_from_tool", "constellation", "time_offset"]:
        assert key in doc
    assert {"covariance", "residual_rms_m", "effects", "gauge", "identifiability"} <= set(doc)
    back = CalibrationResult.from_json(doc)
    np.testing.assert_allclose(back.camera_from_base.position, res.camera_from_base.position)
    np.testing.assert_allclose(
        back.flange_from_tool.quaternion_wxyz, res.flange_from_tool.quaternion_wxyz
    )
    np.testing.assert_allclose(back.constellation, res.constellation)
    np.testing.assert_allclose(back.covariance, res.covariance)
    assert back.parameter_names == res.parameter_names and back.gauge == res.gauge
    assert back.motion_threshold == res.motion_threshold == MOTION_THRESHOLD
    with pytest.raises(UserError):
        CalibrationResult.from_json({"camera_from_base": {}})


def _cut(rec, keep):
    return rec.replace(
        time=rec.time[keep],
        frame_index=rec.frame_index[keep],
        positions=rec.positions[keep],
        status=rec.status[keep],
        temperature=rec.temperature[keep],
        program=None,
        truth=None,
    )


@pytest.mark.parametrize(
    "case, message",
    [
        ("no robot", "no robot log"),
        ("no tool", "no tool"),
        ("no overlap", "overlap"),
        ("one pose", "one robot pose"),
        ("two poses", "distinct robot poses"),
        ("bad effect", "unknown effect"),
    ],
)
def test_bad_input_is_a_clear_user_error(fits, case, message):
    rec = fits[0][0]
    seg = rec.program.segment
    if case == "no robot":
        rec = rec.replace(robot=None)
    elif case == "no tool":
        rec = rec.replace(tool=None)
    elif case == "no overlap":
        rec = rec.replace(robot=dataclasses.replace(rec.robot, time=rec.robot.time + 1e4))
    elif case == "one pose":
        rec = _cut(rec, (seg == 0) & (rec.time < 0.9))
    elif case == "two poses":
        first, second = np.flatnonzero(seg == 0)[:20], np.flatnonzero(seg == 1)[-20:]
        rec = _cut(rec, np.isin(np.arange(rec.n_frames), np.concatenate([first, second])))
    with pytest.raises(UserError, match=message):
        fit(rec, estimate=("no_such_effect",) if case == "bad effect" else ())


def test_probe_data_fix_the_tool_frame(fits):
    """With the tool frame probed at a few static poses, the estimates are the true
    flange←tool and constellation themselves, not a gauge-aligned version."""
    from robtraj.recording import Probe

    rec, _ = fits[2]
    seg = rec.program.segment
    frames = [np.flatnonzero(seg == s)[-5] for s in range(4)]
    tp = rec.truth.tool_pose
    probe = Probe(
        time=rec.time[frames],
        tool_pose=Pose(tp.position[frames], tp.quaternion_wxyz[frames]),
    )
    res = fit(rec.replace(probe=probe))
    assert res.gauge == "probe" and res.converged
    sigma = np.sqrt(np.diag(res.covariance))
    err = np.concatenate(
        [
            _tangent_error(res.camera_from_base, rec.truth.camera_from_base),
            _tangent_error(res.flange_from_tool, rec.truth.flange_from_tool),
            (res.constellation - rec.truth.constellation).reshape(-1),
        ]
    )
    ok = sigma > 0
    assert np.max(np.abs(err[ok] / sigma[ok])) < 4.5
    assert np.sqrt(np.mean((err[ok] / sigma[ok]) ** 2)) < 1.6
