"""Real UR10 + laser tracker data (shared/data/ipa-robot-accuracy): pose-level
calibration, identifiability, and the discrepancy workflow validated across series.

Subsampled to keep the suite fast: 500 evenly spaced poses of each series (the same
length, so every kernel compiles once); the full-data figures are in docs/real_ur10.md.
"""

from pathlib import Path

import numpy as np
import pytest

from robtraj.analysis import _pose_fit as pf

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ipa-robot-accuracy"
pytestmark = pytest.mark.skipif(
    not (DATA / "Series_B" / "measurements_joint_configurations.csv").is_file(),
    reason="ipa-robot-accuracy data not present",
)
N_POSES = 500


@pytest.fixture(scope="module")
def series():
    from robtraj.analysis import real_data as rd

    return {
        "A": rd.load_series("A", DATA).evenly(N_POSES),
        "B": rd.load_series("B", DATA).evenly(N_POSES),
    }


@pytest.fixture(scope="module")
def workflow(series):
    from robtraj.analysis import real_data as rd

    return rd.run_workflow(series)


def _cross(model, key):
    """Cross-series position RMS [m] and orientation RMS [rad]."""
    f = model.cross[key]
    return float(np.sqrt(np.mean(f.position_error**2))), float(np.sqrt(np.mean(f.angle_error**2)))


def test_nominal_rigid_model_explains_the_data_to_about_a_millimetre(workflow):
    nominal = workflow.models[0]
    for name, f in nominal.fitted.items():
        s = f.summary(workflow.noise_m[name])
        assert 0.3 < s["pos_mean_mm"] < 1.5, s
        assert s["pos_max_mm"] < 4.0, s
        assert s["ang_mean_deg"] < 0.2, s
        assert 0 < s["gap_mm"] <= s["pos_rms_mm"]
        # only the 12 rigid parameters are free in the nominal model
        assert f.n_free == 12
    # the tracker's own noise (Series B std) is tens of micrometres: the gap is model error
    assert 0 < workflow.noise_m["B"] < 5e-5


def test_calibration_reports_and_fixes_the_ur10_degeneracies(workflow):
    for f in workflow.calibration.fitted.values():
        dropped = {d["parameter"]: d["confounded_with"] for d in f.identifiability["dropped"]}
        # joint-1 zero ≡ tracker yaw; d1 ≡ tracker z; joint-6 zero ≡ probe roll;
        # d6, a6 ≡ probe offset; d2 + d3 + d4 (parallel axes 2–4) only as a sum
        assert "camera_from_base.rz" in dropped["joint_offset[0]"]
        assert "camera_from_base.tz" in dropped["link_length[0].d"]
        assert "flange_from_probe.rz" in dropped["joint_offset[5]"]
        for p in ("link_length[5].d", "link_length[5].a", "link_length[1].d", "link_length[2].d"):
            assert p in dropped
        assert len(dropped) == 7
        assert f.converged
        params = f.parameters()
        assert "joint_offset[0]" not in params and "joint_offset[1]" in params
        # a well-determined calibration: every remaining parameter has a finite σ
        assert all(np.isfinite(s) and s > 0 for _, s in params.values())
        # kinematic corrections of a UR10: sub-millimetre, sub-milliradian
        lengths = [v for k, (v, _) in params.items() if k.startswith("link_length")]
        assert max(abs(v) for v in lengths) < 3e-3


def test_weights_come_from_the_tracker_std_where_present(series):

    assert series["A"].std is None and series["B"].std is not None
    w = pf._weights(series["B"], (1e-6, 1e-6))
    assert np.ptp(w[:, 0]) > 0  # per-pose weights from Series B's reported std
    std = series["B"].std
    np.testing.assert_allclose(w[:, 0], 1 / (1e-12 + np.mean(std[:, :3] ** 2, 1)))
    np.testing.assert_allclose(w[:, 3], 1 / (1e-12 + np.mean(std[:, 3:] ** 2, 1)))
    wa = pf._weights(series["A"], (1e-6, 1e-6))
    assert np.ptp(wa[:, 0]) == 0


def test_named_effects_reduce_the_cross_series_prediction_error(workflow):
    assert workflow.named, "nothing named"
    assert "link_length" in workflow.named
    for before, after in zip(workflow.models[:-1], workflow.models[1:]):
        for key in ("A->B", "B->A"):
            p0, _ = _cross(before, key)
            p1, _ = _cross(after, key)
            assert p1 < 0.95 * p0, (after.effects, key, p0, p1)
    for step in workflow.steps:
        assert step["predicts_better"] and step["fits_better"]
        assert all(g >= 0.02 for g in step["cross_gain"].values())


def test_overfitting_effects_are_not_named(workflow):
    """A candidate that improves the fitted series (ΔBIC > 0) but not the other series'
    prediction is rejected in that round, never named."""
    for k, step in enumerate(workflow.steps, start=1):
        rejected_now = {e["effect"] for e in workflow.rejected if e["round"] == k}
        assert step["effect"] not in rejected_now
    for entry in workflow.rejected:
        assert entry["fits_better"] and not entry["predicts_better"]
    assert workflow.rejected, "expected at least one effect that only helps the fitted series"


def test_a_rejected_effect_helps_the_fitted_series_but_not_the_other(workflow, series):
    """Independent of the workflow's bookkeeping: refit the first rejected candidate on top
    of what was named before it and compare with that model directly."""
    from robtraj.analysis import real_data as rd

    entry = workflow.rejected[0]
    before = workflow.models[entry["round"] - 1]
    bsig = {k: f.block_sigma for k, f in workflow.models[0].fitted.items()}
    after = rd.evaluate((*before.effects, entry["effect"]), series, block_sigma=bsig)
    for k in series:  # better on the series it was fitted to ...
        assert after.fitted[k].chi2 < before.fitted[k].chi2
    worse = [  # ... but not clearly better predicting the other one, in some direction
        key
        for key in ("A->B", "B->A")
        if _cross(after, key)[0] > (1 - rd.MIN_CROSS_GAIN) * _cross(before, key)[0]
        or _cross(after, key)[1] > (1 - rd.MIN_CROSS_GAIN) * _cross(before, key)[1]
    ]
    assert worse, (entry["effect"], entry["cross_gain"])


def test_report_table_has_the_figures(workflow):
    rows = workflow.table()
    models = {r["model"] for r in rows}
    assert "nominal rigid" in models
    assert any(m.startswith("calibration") for m in models)
    assert {f"+ {e}" for e in workflow.named} <= models
    cols = {r["column"] for r in rows}
    assert cols == {"fit A", "fit B", "A->B", "B->A"}
    for r in rows:
        for k in ("pos_mean_mm", "pos_max_mm", "ang_mean_deg", "ang_max_deg", "gap_mm"):
            assert np.isfinite(r[k])
    md = workflow.markdown()
    assert md.count("\n") == len(rows) + 2


def test_recording_adapter_matches_the_csv_reader():
    from robtraj.analysis import real_data as rd
    from robtraj.importers import import_pose_csv

    rec = import_pose_csv(
        DATA / "Series_B" / "measurements_joint_configurations.csv", preset="ipa-ur10"
    )
    a = rd.series_from_recording(rec, "B")
    b = rd.load_series("B", DATA)
    np.testing.assert_allclose(a.joints, b.joints)
    np.testing.assert_allclose(a.measured[:, 4:], b.measured[:, 4:], atol=1e-12)
    # quaternions up to sign
    dots = np.abs(np.sum(a.measured[:, :4] * b.measured[:, :4], -1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-9)
    np.testing.assert_allclose(a.std, b.std)


def test_pose_model_is_the_package_forward_model(series):
    """The fast pose-level predictor equals `robtraj.model.flange_poses` composed with
    the rigid transforms, with every effect switched on."""
    import jax
    import jax.numpy as jnp
    import jaxlie

    from robtraj.analysis import real_data as rd
    from robtraj.model import camera_from_base_at, flange_poses, ur10

    s = series["B"]
    rng = np.random.default_rng(0)
    theta = rng.normal(0, 1e-3, pf.N_PARAMS)
    theta[pf._SL["joint_compliance"]] = rng.normal(0, 1e-5, 6)
    z0, x0 = s.start
    pred = np.asarray(
        pf._predict_jit(
            jnp.asarray(theta),
            jnp.asarray(z0),
            jnp.asarray(x0),
            jnp.asarray(s.joints),
            jnp.asarray(s.drift_variable),
            jnp.asarray(s.torque),
        )
    )
    eff = pf._effects_of(jnp.asarray(theta))
    q = jnp.asarray(s.joints)
    fl = jax.jit(flange_poses)(ur10(), eff, q, jnp.zeros_like(q))
    z = jaxlie.SE3(jnp.asarray(z0)) @ jaxlie.SE3.exp(jnp.asarray(theta[:6]))
    x = jaxlie.SE3(jnp.asarray(x0)) @ jaxlie.SE3.exp(jnp.asarray(theta[6:12]))
    ref = camera_from_base_at(z, eff, jnp.asarray(s.drift_variable)) @ fl @ x
    pos = (1 + theta[-1]) * np.asarray(ref.translation())
    np.testing.assert_allclose(pred[:, 4:], pos, atol=1e-12)
    pe, ae = rd.pose_errors(pred, np.asarray(ref.wxyz_xyz))
    assert np.max(ae) < 1e-10
    # the rigid-only fast path (nominal fits, cross-series refits) is the same residual
    args = tuple(jnp.asarray(a) for a in (z0, x0, s.joints, s.drift_variable, s.torque, s.measured))
    full = pf._Problem(args, np.ones(pf.N_PARAMS, bool)).residual(theta)
    fast = pf._Problem(args, np.arange(pf.N_PARAMS) < 12).residual(theta)
    np.testing.assert_allclose(fast, full, atol=1e-12)


@pytest.mark.exhaustive
def test_bundle_calibration_agrees_with_the_pose_level_fit():
    """`robtraj.estimate.calibration.fit` on the imported recording (4 virtual points per
    pose, probe gauge) finds the same camera←base as the pose-level fit (about 1 min)."""
    from robtraj.analysis import real_data as rd
    from robtraj.estimate.calibration import fit
    from robtraj.importers import import_pose_csv

    rec = import_pose_csv(
        DATA / "Series_B" / "measurements_joint_configurations.csv", preset="ipa-ur10"
    )
    res = fit(rec)
    pose = rd.fit_poses(rd.series_from_recording(rec, "B"))
    cam = np.concatenate([res.camera_from_base.quaternion_wxyz, res.camera_from_base.position])
    dt, da = rd.transform_difference(cam, pose.camera_from_base)
    assert dt < 1e-3 and np.rad2deg(da) < 0.02
