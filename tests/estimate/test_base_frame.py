"""Measured tool poses in the base frame, through a calibration, against truth."""

import numpy as np
from scipy.spatial.transform import Rotation as R

from robtraj.estimate import errors_against
from robtraj.estimate._base_frame import base_frame_poses
from robtraj.estimate.calibration import fit
from robtraj.sim import simulate


def test_base_frame_poses_match_truth_through_a_calibration():
    # one setup (same seed: same camera placement and tool), two recordings: calibrate on
    # the calibration run, measure the ISO cube run
    cal = fit(simulate("calibration", seed=2, duration=30.0, rate=100.0))
    rec = simulate("iso_cube", seed=2, duration=30.0, rate=100.0)
    bf = base_frame_poses(rec, cal, tcp="calibrated")
    tc, tp = rec.truth.camera_from_base, rec.truth.tool_pose
    r_cb = R.from_quat(tc.quaternion_wxyz, scalar_first=True)
    p_true = r_cb.inv().apply(tp.position - tc.position)
    err = np.linalg.norm(bf.position - p_true, axis=1)
    # the camera-frame pose noise alone, with the same constellation and weighting
    e_cam, _ = errors_against(bf.poses, tp.position, tp.quaternion_wxyz)
    rms = lambda e: np.sqrt(np.nanmean(e**2))
    assert bf.valid.mean() > 0.99
    # Without probe data the tool frame is the one in which the constellation best fits
    # its nominal; the true LEDs sit ~50 µm off nominal, so that frame (and the TCP)
    # differs from the true one by a few tens of µm: a constant offset on top of the noise.
    bias = np.linalg.norm(np.nanmean(bf.position - p_true, axis=0))
    assert bias < 60e-6, bias
    assert rms(err) < np.hypot(rms(e_cam), bias) * 1.3, (rms(err), rms(e_cam), bias)
    q_true = r_cb.inv() * R.from_quat(tp.quaternion_wxyz, scalar_first=True)
    ang = (q_true.inv() * R.from_quat(bf.quaternion_wxyz[bf.valid], scalar_first=True)).magnitude()
    assert np.degrees(np.median(ang)) < 0.1


def test_nominal_tcp_is_the_controllers_tcp_on_the_measured_flange():
    """tcp="nominal": base←flange(measured) · nominal flange←tool, i.e. the point the
    robot was told to move, so a tool-mount error does not show up as robot error."""
    cal = fit(simulate("calibration", seed=2, duration=30.0, rate=100.0))
    rec = simulate("iso_cube", seed=2, duration=30.0, rate=100.0)
    nominal = base_frame_poses(rec, cal)
    calibrated = base_frame_poses(rec, cal, tcp="calibrated")
    # expected: calibrated tool pose · (calibrated flange←tool)⁻¹ · nominal flange←tool
    r_tool = R.from_quat(calibrated.quaternion_wxyz[calibrated.valid], scalar_first=True)
    fc, fn = cal.flange_from_tool, rec.tool.flange_from_tool
    r_fc = R.from_quat(fc.quaternion_wxyz, scalar_first=True)
    r_fn = R.from_quat(fn.quaternion_wxyz, scalar_first=True)
    shift = r_fc.inv().apply(fn.position - fc.position)
    want_p = calibrated.position[calibrated.valid] + r_tool.apply(shift)
    want_q = (r_tool * r_fc.inv() * r_fn).as_quat(scalar_first=True)
    np.testing.assert_allclose(nominal.position[nominal.valid], want_p, atol=1e-12)
    dots = np.abs(np.sum(nominal.quaternion_wxyz[nominal.valid] * want_q, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)
    # the simulated robot has no kinematic error: the controller's TCP reaches the target
    assert np.linalg.norm(nominal.position[0] - rec.program.targets.position[0]) < 2e-4
