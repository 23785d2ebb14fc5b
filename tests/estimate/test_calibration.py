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
    fit,
    robot_world_hand_eye,
)
from robtraj.model import Effects
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
    truth = rec.truth
    sigma = np.sqrt(np.diag(res.covariance))
    p_true, fft_true = align_to_gauge(
        res, truth.constellation, truth.flange_from_tool, led_ids=rec.tool.led_ids
    )
    err = np.concatenate(
        [
            _tangent_error(res.camera_from_base, truth.camera_from_base),
            _tangent_error(res.flange_from_tool, fft_true),
            (res.constellation - p_true).reshape(-1),
        ]
    )
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


# The optimum of the hand-written Levenberg–Marquardt loop this package used before its
# Optimistix engine, on `fits[0]` (seed 0): `fit(simulate("calibration", seed=0,
# duration=16.0, rate=25.0))` at commit 0228a06 (camera←base and flange←tool as
# ``wxyz_xyz``, the constellation [m], σ of every covariance parameter).
_REF_CAMERA_FROM_BASE = np.array(
    [
        -0.4914477644828749,
        -0.5049375819075721,
        -0.49161652823284513,
        0.511693582459662,
        0.05336750417404457,
        1.0362204686021081,
        3.182214262016808,
    ]
)
_REF_FLANGE_FROM_TOOL = np.array(
    [
        0.9999958735318327,
        0.0021242658659808827,
        0.0013779898902999588,
        -0.0013570400507367435,
        -0.0006368696570731823,
        -0.0003062918753864176,
        0.10003242474585822,
    ]
)
_REF_CONSTELLATION = np.array(
    [
        [-0.00010884873857105273, 1.5384379716329335e-06, 0.04992250079284564],
        [0.03210932236317282, 3.434992597977682e-07, 0.038270101951484496],
        [0.01608073403267628, 0.027903407941245618, 0.03826973226074101],
        [-0.016014001834162128, 0.027799026126255788, 0.03829555376656948],
        [-0.03208730656810736, -6.902040837062889e-06, 0.03825274190480787],
        [-0.016092532617378096, -0.027859602011810848, 0.038307765930194394],
        [0.01603989567982907, -0.027825112380916475, 0.03829047419090997],
        [0.04615525431436462, 0.014304190932056442, 0.012936336578105063],
        [0.031049417105495674, 0.03696210090850752, 0.012948848261308061],
        [0.006236166221426848, 0.04784602487893566, 0.012986990486376351],
        [-0.02069355033548803, 0.04363838596056426, 0.012940952255126037],
        [-0.0410247835212283, 0.025567680145932376, 0.013013107802278174],
        [-0.04819900146613541, -0.0006686495299569669, 0.012944514572211657],
        [-0.04028178166853305, -0.02672937452705617, 0.012968531012073669],
        [-0.01946923215639346, -0.044215651102017306, 0.012962408876988832],
        [0.007629663460291066, -0.04775582070812968, 0.012910670632001669],
        [0.032150689291039015, -0.03607205215932873, 0.01302698149808347],
        [0.04651989643770147, -0.012889534370675826, 0.012915594969974001],
    ]
)
_REF_SIGMA = np.array(
    [
        4.02182018708325e-06,
        5.282994396705727e-06,
        4.740136937541567e-06,
        3.5276615183601805e-06,
        3.766689259716931e-06,
        3.8093962668067414e-06,
        1.5246619145389348e-06,
        1.554637689863811e-06,
        2.7783049741993773e-06,
        3.380462967880842e-05,
        3.610799908063564e-05,
        2.950369176096821e-05,
        1.3656952908857247e-06,
        1.310975340855565e-06,
        1.2521090818962327e-06,
        1.4796888634084797e-06,
        1.5777085054878304e-06,
        1.6590877332982674e-06,
        1.7647642437047598e-06,
        1.5500115689653374e-06,
        1.8040104674902794e-06,
        1.8613120678435984e-06,
        1.7582281380951338e-06,
        2.1372057018807253e-06,
        1.596198439992793e-06,
        1.8563242319526408e-06,
        2.0677294661395348e-06,
        1.5586383152836599e-06,
        1.5398524062166812e-06,
        1.7096273630895263e-06,
        1.5499085718556598e-06,
        1.4281071708906038e-06,
        1.6122881292608531e-06,
        4.740336603366111e-06,
        4.5114773804976865e-06,
        4.297828596986225e-06,
        4.023757912209198e-06,
        4.004959372383511e-06,
        3.7201798755493876e-06,
        4.634253498702437e-06,
        4.878844320995107e-06,
        4.3401727083512375e-06,
        0.0,
        0.0,
        0.0,
        7.429904649120566e-06,
        7.2029212185939325e-06,
        6.5557190581638366e-06,
        5.527399874200362e-06,
        5.23015184807713e-06,
        5.024309710879335e-06,
        4.8421854608316874e-06,
        4.764689987791282e-06,
        4.5288595331260745e-06,
        4.74154146979975e-06,
        4.926627019430992e-06,
        4.482161133696506e-06,
        3.91794487268228e-06,
        4.035729178011863e-06,
        3.710963923389052e-06,
        4.014876447725909e-06,
        3.9952573111432175e-06,
        3.7665019031406986e-06,
        5.0162963850945065e-06,
        4.744789940238496e-06,
        4.552739030388322e-06,
    ]
)


def test_same_optimum_as_the_previous_solver(fits):
    """Both solvers minimise the same χ²: their optima agree to 0.01σ of every parameter
    (a fraction of σ that no change of the model or the weights would stay below)."""
    _, res = fits[0]
    err = np.concatenate(
        [
            _tangent_error(res.camera_from_base, _pose(_REF_CAMERA_FROM_BASE)),
            _tangent_error(res.flange_from_tool, _pose(_REF_FLANGE_FROM_TOOL)),
            (res.constellation - _REF_CONSTELLATION).reshape(-1),
        ]
    )
    ok = _REF_SIGMA > 0
    assert np.all((np.sqrt(np.diag(res.covariance)) > 0) == ok)
    assert np.max(np.abs(err[ok]) / _REF_SIGMA[ok]) < 0.01
    np.testing.assert_allclose(np.sqrt(np.diag(res.covariance))[ok], _REF_SIGMA[ok], rtol=1e-3)


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
