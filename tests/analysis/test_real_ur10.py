"""Real UR10 + laser tracker data (shared/data/ipa-robot-accuracy): pose-level
calibration, identifiability, and the discrepancy workflow validated across series.

Subsampled to keep the suite fast: 500 evenly spaced poses of each series (the same
length, so every kernel compiles once); the full-data figures are in docs/real_ur10.md
and `test_full_data_figures` (exhaustive, on demand).
"""

from pathlib import Path

import numpy as np
import pytest

from robtraj.analysis import _pose_fit as pf
from robtraj.estimate import _pose_problem as pp

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

    # the dictionary's joint harmonics offered besides the library and the maps
    return rd.run_workflow(series, candidates=rd.CANDIDATES + rd.DICTIONARY)


def _rms(f):
    """Position RMS [m] and orientation RMS [rad] of a fit's or a prediction's errors."""
    return float(np.sqrt(np.mean(f.position_error**2))), float(np.sqrt(np.mean(f.angle_error**2)))


def test_nominal_rigid_model_explains_the_data_to_about_a_millimetre(workflow):
    for name, f in workflow.nominal.fitted.items():
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
        assert "flange_from_tool.rz" in dropped["joint_offset[5]"]
        for p in ("link_length[5].d", "link_length[5].a", "link_length[1].d", "link_length[2].d"):
            assert p in dropped
        assert len(dropped) == 7
        # Hayati's tilt is estimated only where consecutive axes are parallel (links 2
        # and 3), never for the last link's axis (≡ probe orientation)
        free = {n for n, f in zip(pf.parameter_names(), f.free) if f and "twist" in n}
        assert free == {f"link_twist[{j}].alpha" for j in range(5)} | {
            "link_twist[1].beta",
            "link_twist[2].beta",
        }
        assert f.converged
        params = f.parameters()
        assert "joint_offset[0]" not in params and "joint_offset[1]" in params
        # a well-determined calibration: every remaining parameter has a finite σ
        assert all(np.isfinite(s) and s > 0 for _, s in params.values())
        # kinematic corrections of a UR10: sub-millimetre, sub-milliradian
        lengths = [v for k, (v, _) in params.items() if k.startswith("link_length")]
        assert max(abs(v) for v in lengths) < 3e-3
        twists = [v for k, (v, _) in params.items() if k.startswith("link_twist")]
        assert len(twists) == 7 and max(abs(v) for v in twists) < 3e-3


def test_weights_come_from_the_tracker_std_where_present(series):

    assert series["A"].std is None and series["B"].std is not None
    w = pf._weights(series["B"], (1e-6, 1e-6))
    assert np.ptp(w[:, 0]) > 0  # per-pose weights from Series B's reported std
    std = series["B"].std
    np.testing.assert_allclose(w[:, 0], 1 / (1e-12 + np.mean(std[:, :3] ** 2, 1)))
    np.testing.assert_allclose(w[:, 3], 1 / (1e-12 + np.mean(std[:, 3:] ** 2, 1)))
    wa = pf._weights(series["A"], (1e-6, 1e-6))
    assert np.ptp(wa[:, 0]) == 0


def test_each_series_names_the_maps_and_the_geometry_by_its_own_cross_validation(workflow):
    """Each series names, by cross-validation inside itself, every joint's angle error
    map and the link geometry, each step lowering its held-out error by ≥ 2 %; no
    harmonic of the dictionary is named (the maps carry what they could)."""
    from robtraj.analysis import real_data as rd

    for key, named in workflow.named.items():
        assert {"joint_map", "link_twist", "link_length"} <= set(named), (key, named)
        assert not any("harmonic" in n for n in named), (key, named)
    for st in workflow.steps:
        assert st["cv_gain"] >= rd.MIN_CV_GAIN and st["predicts_better"]
        assert st["cv"]["pos_rms_m"] < st["cv_before"]["pos_rms_m"]
    for key, sel in workflow.selections.items():
        for before, after in zip(sel.steps[:-1], sel.steps[1:]):
            assert after["cv_before"] == pytest.approx(before["cv"], rel=0.02)


def test_the_validation_series_takes_no_part_in_naming(workflow, series):
    """Series A's selection on its own (no Series B anywhere) names the same effects with
    the same cross-validation figures as the workflow run on both."""
    from robtraj.analysis import _pose_selection as ps, real_data as rd

    alone = ps.select(
        series["A"],
        pf.fit_poses(series["A"]),
        rd.CANDIDATES + rd.DICTIONARY,
        prior_grid=rd.MAP_PRIOR_GRID,
    )
    assert alone.named == workflow.named["A"]
    for a, b in zip(alone.steps, workflow.selections["A"].steps):
        assert a["cv"] == pytest.approx(b["cv"], rel=1e-6)


def test_the_named_models_predict_the_other_series_better(workflow, series):
    """Validation on the series that took no part: each named model predicts the other
    series better than the nominal one and than the library's named model (link twists,
    lengths, shoulder and elbow compliance, without the maps), by more than five
    standard errors of the paired per-pose difference; and within the issue's targets
    (mean ≤ 0.35 mm, ≤ 0.07°)."""
    from robtraj.analysis import real_data as rd

    bsig = {k: f.block_sigma for k, f in workflow.nominal.fitted.items()}
    library = rd.evaluate(
        ("link_twist", "link_length", "joint_compliance[1,2]"), series, block_sigma=bsig
    )
    final = workflow.final
    for key in ("A->B", "B->A"):
        got = final.cross[key]
        for ref in (workflow.nominal.cross[key], library.cross[key]):
            d = ref.position_error - got.position_error
            assert d.mean() > 5 * d.std() / np.sqrt(d.size), key
            assert _rms(got)[1] < _rms(ref)[1], key
        s = got.summary()
        assert s["pos_mean_mm"] <= 0.35 and s["ang_mean_deg"] <= 0.07, (key, s)
        # the gain each step made across series is reported beside the naming figures
    assert all(
        set(st["cross_gain"]) == {f"{st['series']}->{'B' if st['series'] == 'A' else 'A'}"}
        for st in workflow.steps
    )


def test_overfitting_effects_are_not_named(workflow):
    """A candidate that fits its series better (ΔBIC > 0) but does not lower its
    cross-validation error by 2 % is rejected in that round, never named; on Series A
    the joint harmonics are (the old cross-series rule rejected them too)."""
    for st in workflow.steps:
        now = {
            e["effect"]
            for e in workflow.rejected
            if e["round"] == st["round"] and e["series"] == st["series"]
        }
        assert st["effect"] not in now
    for entry in workflow.rejected:
        assert entry["fits_better"] and not entry["predicts_better"]
    harmonics = {
        e["effect"] for e in workflow.rejected if e["series"] == "A" and "harmonic" in e["effect"]
    }
    assert len(harmonics) >= 6, harmonics


def test_a_rejected_effect_helps_the_fitted_series_but_not_its_cross_validation(workflow, series):
    """Independent of the selection's bookkeeping (one step from the current model):
    refit the first rejected candidate on top of what was named before it, and the model
    without it; the candidate lowers the series' χ² but, with each model's blocked
    cross-validation taken at its own optimum, not its held-out error by 2 %."""
    from robtraj.analysis import _pose_cv as cv, real_data as rd

    entry = next(e for e in workflow.rejected if "harmonic" not in e["effect"])
    key = entry["series"]
    sel = workflow.selections[key]
    before = sel.named[: entry["round"] - 1]
    s = series[key]
    bsig = workflow.nominal.fitted[key].block_sigma
    prior = sel.fits[entry["round"] - 1].map_prior
    fits = [
        pf.fit_poses(s, estimate=est, block_sigma=bsig, map_prior=prior)
        for est in (tuple(before), (*before, entry["effect"]))
    ]
    assert fits[1].chi2 < fits[0].chi2
    errors = []
    for f in fits:
        pr = pf.map_prior_of(f.estimated, prior)
        d = pf._data(f.z0, f.x0, s, pf._weights(s, bsig), False, pr)
        lin = pf.linearise(f.theta, d, pf.regions(s))
        lam = pr.dense(f.theta.size) if pr.size else None
        errors.append(cv.cv_error(lin, cv.region_steps(lin, f.free, lam)))
    assert cv.gain(errors[0], errors[1]) < rd.MIN_CV_GAIN, (entry["effect"], errors)


def test_report_table_has_the_figures(workflow):
    rows = workflow.table()
    models = {r["model"] for r in rows}
    assert "nominal rigid" in models
    assert any(m.startswith("calibration") for m in models)
    for key, named in workflow.named.items():
        assert {f"+ {e} (named on {key})" for e in named} <= models
    cols = {r["column"] for r in rows}
    assert cols == {"fit A", "fit B", "A->B", "B->A"}
    for r in rows:
        for k in ("pos_mean_mm", "pos_max_mm", "ang_mean_deg", "ang_max_deg", "gap_mm"):
            assert np.isfinite(r[k])
    md = workflow.markdown()
    assert md.count("\n") == len(rows) + 2


def test_the_maps_in_words_numbers_and_a_figure(workflow, tmp_path):
    """Every named map is reported in words (joint, RMS, peak, strongest periodic
    component, the range of the data), with its knots, values and posterior σ (JSON),
    and drawn with its ±1σ band."""
    import json

    from robtraj.report import map_figure

    doc = json.loads(json.dumps(workflow.to_json()))
    maps = [st for st in doc["steps"] if "term" in st]
    assert {st["series"] for st in maps} == {"A", "B"}
    for st in maps:
        words = st["term"]["words"]
        assert len(words) == 6
        for j, w in enumerate(words, start=1):
            assert w.startswith(f"joint {j} angle error map: rms ") and "cycles/rev" in w
            assert f"over q{j} ∈ [" in w and "(where the data are)" in w
        for m in st["term"]["maps"].values():
            assert len(m["knots_rad"]) == len(m["value_rad"]) == len(m["sigma_rad"]) > 10
            assert np.all(np.diff(m["knots_rad"]) > 0)
            sig = np.asarray(m["sigma_rad"], float)
            assert np.all(sig[np.isfinite(sig)] > 0)
        assert st["term"]["prior"]["sigma_f_rad"] > 0
    png = map_figure(tmp_path / "maps.png", maps[-1]["term"]["maps"], "maps")
    assert png.stat().st_size > 10_000


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
    the rigid transforms, with every effect switched on (the maps from their two active
    knots there, from every hat feature in the model)."""
    import jax
    import jax.numpy as jnp
    import jaxlie

    from robtraj.analysis import real_data as rd
    from robtraj.model import camera_from_base_at, flange_poses, ur10

    s = series["B"]
    rng = np.random.default_rng(0)
    theta = rng.normal(0, 1e-3, pf.n_params(True))
    theta[pf._SL["joint_compliance"]] = rng.normal(0, 1e-5, 6)
    z0, x0 = s.start
    w = np.ones((s.n, 6))
    pred = np.asarray(pp.predict_probe_poses(jnp.asarray(theta), pf._data(z0, x0, s, w, False)))
    eff = pp.pose_effects(jnp.asarray(theta))
    q = jnp.asarray(s.joints)
    fl = jax.jit(flange_poses)(ur10(), eff, q, jnp.zeros_like(q))
    z = jaxlie.SE3(jnp.asarray(z0)) @ jaxlie.SE3.exp(jnp.asarray(theta[:6]))
    x = jaxlie.SE3(jnp.asarray(x0)) @ jaxlie.SE3.exp(jnp.asarray(theta[6:12]))
    ref = camera_from_base_at(z, eff, jnp.asarray(s.drift_variable)) @ fl @ x
    pos = (1 + theta[pf._SL["tracker_scale"]][0]) * np.asarray(ref.translation())
    np.testing.assert_allclose(pred[:, 4:], pos, atol=1e-12)
    pe, ae = rd.pose_errors(pred, np.asarray(ref.wxyz_xyz))
    assert np.max(ae) < 1e-10
    # the rigid-only fast path (nominal fits, cross-series refits) is the same residual
    full = pp.pose_residual(jnp.asarray(theta), pf._data(z0, x0, s, w, False))
    fast = pp.pose_residual(jnp.asarray(theta), pf._data(z0, x0, s, w, True))
    np.testing.assert_allclose(np.asarray(fast), np.asarray(full), atol=1e-12)
    # the chain-rule Jacobian (closed-form flange twists) equals forward mode through
    # the whole residual, every effect included
    d = pf._data(z0, x0, s, w, False)
    _, jac = jax.jit(pp._jacobian)(jnp.asarray(theta), d)
    ref = jax.jit(jax.jacfwd(pp._raw_residual))(jnp.asarray(theta), d)
    scale = np.abs(np.asarray(ref)).max((0, 1))
    scale = np.where(scale > 0, scale, 1.0)  # compliance of joints without gravity torque
    ref = np.asarray(ref)[..., : pf.N_PARAMS]  # the maps' columns: test_pose_maps.py
    np.testing.assert_allclose(
        np.asarray(jac) / scale[: pf.N_PARAMS], ref / scale[: pf.N_PARAMS], atol=1e-12
    )


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


# The calibration (joint_offset + link_length) of the pose-level fit's own
# Levenberg–Marquardt loop before the package's one engine replaced it:
# `rd.evaluate(("joint_offset", "link_length"), series)` on the `series` fixture at
# commit 0228a06 (θ: `pf.parameter_names()` order of that commit, without
# `link_twist`; tangent corrections around `series[k].start`; poses ``wxyz_xyz``;
# cross-series position RMS [m]).
_REF = {
    "A": {
        "theta": [
            -3.3629316899477565e-05,
            0.001249394804960857,
            -0.0014251250469982512,
            0.0013022890620016097,
            0.0008680803259676016,
            0.0009341166020191006,
            1.496075571212629e-05,
            8.505700967082946e-06,
            0.0001784204414468008,
            -0.00024354076165416873,
            -0.0003223132163147706,
            0.0020087100042706,
            0.0,
            -8.866560009383898e-05,
            -0.00013830746933405532,
            -0.0009834047547905885,
            -0.0009723560689561151,
            0.0,
            0.0,
            7.201931739590527e-05,
            0.0,
            -0.0011104892674874277,
            0.0,
            0.00043106557676271876,
            0.00045964631628262533,
            2.0815141818764686e-06,
            0.0001239189550670319,
            0.0001533943823619564,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ],
        "camera_from_base": [
            0.9653829750982625,
            0.005190015383035436,
            -0.0024337543047101063,
            -0.2607735645550281,
            2.6737781787583814,
            -1.531452448309796,
            -1.3073479917715547,
        ],
        "flange_from_probe": [
            -0.707776036295477,
            0.0003308006588541236,
            0.0008856073624257115,
            0.70643625948587,
            -7.328216812142739e-05,
            0.00022821877746429374,
            0.09308099442566393,
        ],
        "dropped": [
            "joint_offset[0]",
            "joint_offset[5]",
            "link_length[0].d",
            "link_length[1].d",
            "link_length[2].d",
            "link_length[5].a",
            "link_length[5].d",
        ],
    },
    "B": {
        "theta": [
            -0.0008975298452164088,
            -0.000857686068890352,
            -0.0007386809987402282,
            -0.0004053329561646103,
            0.0002714171178567778,
            -0.001431208295637777,
            0.00033240234776859846,
            -0.0006135225362520174,
            0.00011433302493335283,
            0.0020626749346489316,
            0.00045449405014001226,
            -0.0003409079387855988,
            0.0,
            0.00017218402277372632,
            -0.00012504353342654746,
            1.4673848466231342e-05,
            -0.0006721628417941042,
            0.0,
            0.0,
            2.632362391167554e-05,
            0.0,
            -0.001208633094973096,
            0.0,
            0.00021390593637080253,
            9.148922170761957e-05,
            -8.938341406460667e-05,
            9.812314514968621e-05,
            0.00022314764323370475,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ],
        "camera_from_base": [
            0.9847649752345459,
            0.00010853286278305141,
            -0.0015176671332285349,
            0.17388395112371496,
            0.5081566966802539,
            -3.568209592515225,
            -1.2256098842228915,
        ],
        "flange_from_probe": [
            0.7071162508383659,
            -0.00024430495757703685,
            -0.001289089320620017,
            -0.7070960941513563,
            -0.0003421934216460352,
            0.00021867262635917508,
            0.09326218454312371,
        ],
        "dropped": [
            "joint_offset[0]",
            "joint_offset[5]",
            "link_length[0].d",
            "link_length[1].d",
            "link_length[2].d",
            "link_length[5].a",
            "link_length[5].d",
        ],
    },
    "A->B": 0.0006121120028604851,
    "B->A": 0.0006333549318759984,
}


def test_same_optimum_as_the_previous_solver(series):
    """Same calibration as the previous solver: parameters to 1 µm / 1 µrad, the same
    parameters fixed, cross-series errors to 1 µm."""
    from robtraj.analysis import real_data as rd

    cal = rd.evaluate(("joint_offset", "link_length"), series)
    twist = pf._SL["link_twist"]
    for k, f in cal.fitted.items():
        ref = _REF[k]
        assert sorted(d["parameter"] for d in f.identifiability["dropped"]) == ref["dropped"]
        harmonic = pf._SL["joint_harmonic"]
        assert not np.any(f.theta[twist]) and not np.any(f.theta[harmonic])
        theta = np.delete(
            f.theta,
            np.r_[np.arange(twist.start, twist.stop), np.arange(harmonic.start, harmonic.stop)],
        )
        np.testing.assert_allclose(theta, ref["theta"], rtol=0, atol=1e-6)
        for got, want in (
            (f.camera_from_base, ref["camera_from_base"]),
            (f.flange_from_probe, ref["flange_from_probe"]),
        ):
            dt, da = rd_transform_difference(got, np.asarray(want))
            assert dt < 1e-6 and da < 1e-6
    for key in ("A->B", "B->A"):
        assert abs(_rms(cal.cross[key])[0] - _REF[key]) < 1e-6


def rd_transform_difference(a, b):
    from robtraj.analysis import real_data as rd

    return rd.transform_difference(a, b)


def test_series_a_and_b_agree_within_their_robust_sigma(series):
    """The same robot measured twice: each effect parameter estimated on A and on B should
    agree within 2 combined σ (≈ 95 % of parameters where the σ are honest). The
    Gauss–Newton σ assume the residual is noise; here it is mostly model error shared by
    neighbouring poses, and they are too small to cover the A–B difference; the quoted σ
    (with the joint-space region jackknife and the model-error field) do, in ≥ 90 % of
    the parameters (all poses and the richer models: benchmarks/ur10_sigma_agreement.py)."""
    estimate = ("link_length", "joint_offset")
    a, b = (pf.fit_poses(series[k], estimate=estimate) for k in ("A", "B"))
    pa, pb = a.parameters(), b.parameters()
    shared = sorted(set(pa) & set(pb))
    assert len(shared) >= 8, shared
    idx = [pf.parameter_names().index(n) for n in shared]
    diff = np.array([pa[n][0] - pb[n][0] for n in shared])

    def agree(sa, sb):
        return np.mean(np.abs(diff) <= 2 * np.hypot(sa[idx], sb[idx]))

    assert agree(a.sigma, b.sigma) >= 0.9, (shared, diff)
    assert agree(a.sigma_model, b.sigma_model) < 0.9


@pytest.mark.exhaustive
def test_full_data_figures():
    """All poses (about 4 min): each series' named model predicts the other within the
    issue's targets (mean ≤ 0.35 mm, ≤ 0.07°), and the maps fitted on A and on B agree:
    over the knots both reach, each joint's two maps correlate better at their own
    angles than shifted against each other by 0.1 rad or more (the error is locked to
    the joint angle)."""
    from robtraj.analysis import real_data as rd

    series = {k: rd.load_series(k, DATA) for k in ("A", "B")}
    wf = rd.run_workflow(series)
    for key in ("A->B", "B->A"):
        s = wf.final.cross[key].summary()
        assert s["pos_mean_mm"] <= 0.35 and s["ang_mean_deg"] <= 0.07, (key, s)
    maps = {k: wf.final.fitted[k].maps() for k in ("A", "B")}
    for j in range(1, 7):
        a, b = maps["A"][j], maps["B"][j]
        both = a["estimated"] & b["estimated"]
        k = int(round(0.1 / (2 * np.pi / both.size)))

        def corr(shift):
            vb = np.roll(b["value"], shift)
            on = both & np.roll(both, shift)
            return np.corrcoef(a["value"][on], vb[on])[0, 1]

        shifted = [corr(sh) for sh in range(k, 3 * k + 1)] + [
            corr(-sh) for sh in range(k, 3 * k + 1)
        ]
        assert corr(0) > max(shifted), (j, corr(0), max(shifted))
