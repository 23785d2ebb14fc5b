"""TUM export and absolute pose error, checked against the evo package."""

import numpy as np
from evo.core import metrics
from evo.tools import file_interface

from robtraj.analysis import absolute_pose_error, write_tum
from robtraj.analysis._quat import quat_multiply, quat_normalize


def test_ape_agrees_with_evo(tmp_path):
    rng = np.random.default_rng(5)
    n = 500
    t = 100.0 + np.arange(n) * 0.01
    p_true = np.column_stack([np.sin(t), np.cos(0.5 * t), 0.1 * t])
    q_true = quat_normalize(rng.normal(size=(n, 4)))
    p_meas = p_true + rng.normal(0, 2e-4, (n, 3))
    dq = quat_normalize(np.column_stack([np.ones(n), rng.normal(0, 1e-3, (n, 3))]))
    q_meas = quat_multiply(q_true, dq)
    p_meas[17] = np.nan  # an unseen frame is left out of the file
    ours_t, ours_r = absolute_pose_error(p_meas, q_meas, p_true, q_true)
    ok = np.isfinite(ours_t)

    ref = file_interface.read_tum_trajectory_file(
        str(write_tum(tmp_path / "truth.tum", t, p_true, q_true))
    )
    est = file_interface.read_tum_trajectory_file(
        str(write_tum(tmp_path / "meas.tum", t, p_meas, q_meas))
    )
    assert est.num_poses == n - 1 and ref.num_poses == n
    assert np.allclose(est.positions_xyz, p_meas[ok], atol=1e-9)
    assert np.allclose(
        np.abs(np.sum(est.orientations_quat_wxyz * q_meas[ok], axis=1)), 1, atol=1e-12
    )
    # evo needs equal-length, matched trajectories: drop the same frame from the reference
    ref.reduce_to_ids(np.flatnonzero(ok))
    for relation, ours in [
        (metrics.PoseRelation.translation_part, ours_t[ok]),
        (metrics.PoseRelation.rotation_angle_rad, ours_r[ok]),
    ]:
        ape = metrics.APE(relation)
        ape.process_data((ref, est))
        assert np.allclose(ape.error, ours, atol=1e-8)
        stats = ape.get_all_statistics()
        assert np.isclose(stats["rmse"], np.sqrt(np.mean(ours**2)), rtol=1e-6)
        assert np.isclose(stats["max"], ours.max(), rtol=1e-6)
