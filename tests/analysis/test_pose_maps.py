"""Joint angle error maps in the pose-level fit, on synthetic pose series with known
truth: the simulator's unmodelled periodic joint error recovered by a map within its
posterior σ, the normal equations with the maps' sparse block against automatic
differentiation of the pure residual, the one-step blocked cross-validation against a
refit, and the quoted σ under a smooth model error no estimated effect models."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from robtraj.analysis import _pose_cv as cv, _pose_fit as pf, real_data as rd
from robtraj.estimate import _pose_problem as pp
from robtraj.sim import POSE_NOISE, UR10_RANGES, PeriodicJointError, static_pose_series

NOISE = POSE_NOISE


def _series(n, seed, hidden=(), name="S"):
    """`n` static poses of a nominal UR10 whose logged joint angles carry the `hidden`
    unmodelled errors (`robtraj.sim`), measured with `NOISE`."""
    return rd.PoseSeries(name, *static_pose_series(n, seed, hidden))


def test_a_map_recovers_a_hidden_high_harmonic_joint_error_within_its_posterior_sigma():
    """17 cycles per revolution on joint 2 (0.3 mrad, the simulator's
    `PeriodicJointError`, outside the forward model): the fitted map agrees with the
    error at its knots within 3 posterior σ (plus the linear interpolant's own error
    bound, A·(hω)²/8) at ≥ 95 % of the knots the data reach, and it says so in words."""
    amp, cycles, phase = 3e-4, 17, 0.7
    s = _series(2000, 0, [PeriodicJointError(2, cycles, amp, phase)])
    f = pf.fit_poses(s, estimate=("joint2_map",), block_sigma=NOISE)
    assert f.converged
    m = f.maps()[2]
    k = m["knots"]
    lo, hi = UR10_RANGES[1]
    inside = m["estimated"] & (((k - lo) % (2 * np.pi)) <= hi - lo)
    truth = amp * np.sin(cycles * k + phase)
    h = 2 * np.pi / k.size
    bound = amp * (h * cycles) ** 2 / 8
    err = np.abs(m["value"] - truth)[inside]
    sig = m["sigma"][inside]
    assert np.all(np.isfinite(sig)) and np.all(sig > 0)
    assert np.mean(err <= 3 * sig + bound) >= 0.95, (np.median(err), np.median(sig), bound)
    # the σ are not so wide that anything would pass
    assert np.median(sig) < amp / 10
    words = rd.map_report(f, s)["words"][0]
    assert words.startswith("joint 2 angle error map") and "17 cycles/rev" in words
    # without the map the same data leave the error in the residual
    f0 = pf.fit_poses(s, block_sigma=NOISE)
    assert f.summary()["pos_rms_mm"] < 0.5 * f0.summary()["pos_rms_mm"]


def test_pose_normal_equations_with_maps_are_those_of_the_pure_residual():
    """``H``, ``b``, cost of `pose_normal` (dense columns, the maps' block from their
    active knots, the prior) against ``jax.jacfwd`` of `_raw_residual` with every entry
    of θ non-zero, on 40 poses."""
    s = _series(40, 1)
    p = pf.n_params(True)
    rng = np.random.default_rng(5)
    theta = rng.normal(0, 1e-4, p)
    theta[pf._SL["joint_compliance"]] = rng.normal(0, 1e-6, 6)
    prior = pf.map_prior_of(("joint_map",))
    w = rng.uniform(0.5, 2.0, (s.n, 6)) * np.array([1e6] * 3 + [1e4] * 3) ** 2
    z0, x0 = s.start
    d = pf._data(z0, x0, s, w, False, prior)
    h, b, c = jax.jit(pf.pose_normal)(jnp.asarray(theta), d)
    r = np.asarray(pp._raw_residual(jnp.asarray(theta), d))
    j = np.asarray(jax.jit(jax.jacfwd(pp._raw_residual))(jnp.asarray(theta), d))
    sw = np.sqrt(w)
    rw, jw = (sw * r).reshape(-1), (sw[..., None] * j).reshape(-1, p)
    lam = prior.dense(p)
    want_h = jw.T @ jw + lam
    scale = np.sqrt(np.diag(want_h))
    # the compliance of a joint without gravity torque (joints 1 and 6): no column
    scale = np.where(scale > 1e-9 * np.median(scale), scale, 1.0)
    np.testing.assert_allclose(
        np.asarray(h) / np.outer(scale, scale), want_h / np.outer(scale, scale), atol=1e-10
    )
    np.testing.assert_allclose(
        np.asarray(b) / scale, (-(jw.T @ rw) - lam @ theta) / scale, atol=1e-10 * np.sqrt(c)
    )
    np.testing.assert_allclose(c, rw @ rw + theta @ lam @ theta, rtol=1e-12)


def _linearisation_point(n, seed, rng_seed):
    """A synthetic series of `n` poses, θ's size with the maps, a generator, a random θ
    near zero and random per-pose weights (position ~1/µm², rotation ~1/(100 µrad)²)."""
    s = _series(n, seed)
    p = pf.n_params(True)
    rng = np.random.default_rng(rng_seed)
    theta = rng.normal(0, 1e-4, p)
    w = rng.uniform(0.5, 2.0, (s.n, 6)) * np.array([1e6] * 3 + [1e4] * 3) ** 2
    return s, p, rng, theta, w


def test_the_whitened_jacobian_rows_are_those_of_the_pure_residual():
    """`jacobian_rows` (per component, sparse, maps' columns from the active knots)
    against ``jax.jacfwd`` of `_raw_residual`, whitened, on a subset of columns."""
    from robtraj.estimate import jacobian_rows

    s, p, rng, theta, w = _linearisation_point(40, 2, 6)
    z0, x0 = s.start
    d = pf._data(z0, x0, s, w, False, pf.map_prior_of(("joint_map",)))
    lin = pf.linearise(theta, d, np.zeros(s.n, int))
    cols = np.flatnonzero(rng.uniform(size=p) < 0.5)
    rows = jacobian_rows(
        lin.j, np.sqrt(w), lin.offset, lin.map_index, lin.map_weight, p - pf.N_PARAMS, cols
    )
    j = np.asarray(jax.jit(jax.jacfwd(pp._raw_residual))(jnp.asarray(theta), d))
    want = np.sqrt(w)[..., None] * j[:, :, cols]
    got = np.stack([r.toarray() for r in rows], 1)
    np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())


def test_the_per_region_normal_equations_are_those_of_each_region_alone():
    """`linearise`'s `h_g`, `b_g`, cost per region (one product over each region's own
    poses) against `pose_normal` with the weights of the other regions' poses zero, maps
    included."""
    s, p, rng, theta, w = _linearisation_point(60, 1, 7)
    z0, x0 = s.start
    label = pf.regions(s)
    assert label.max() >= 2
    lin = pf.linearise(theta, pf._data(z0, x0, s, w, False), label)
    costs = []
    normal = jax.jit(pf.pose_normal)
    for g in range(label.max() + 1):
        w_g = np.where((label == g)[:, None], w, 0.0)
        h, b, c = normal(jnp.asarray(theta), pf._data(z0, x0, s, w_g, False))
        scale = np.sqrt(np.diag(np.asarray(h)))
        scale = np.where(scale > 1e-9 * np.median(scale), scale, 1.0)
        np.testing.assert_allclose(
            lin.h_g[g] / np.outer(scale, scale), np.asarray(h) / np.outer(scale, scale), atol=1e-12
        )
        np.testing.assert_allclose(lin.b_g[g], np.asarray(b), rtol=1e-10, atol=1e-10 * abs(b).max())
        costs.append(float(c))
    np.testing.assert_allclose(lin.cost, sum(costs), rtol=1e-12)


@pytest.mark.parametrize("woodbury", [True, False])
def test_the_left_out_systems_equal_direct_solves_of_each_region(woodbury, monkeypatch):
    """`RegionSystems` (the map block inverted once and corrected on each region's own
    knots; or, where that inverse fails, one solve per region) against a direct solve
    of ``(H + Λ − H_g) δ = b − Λθ − b_g`` on the free entries per region, and of the
    whole series."""
    if not woodbury:
        monkeypatch.setattr(cv._Downdates, "of", classmethod(lambda cls, a, rhs: None))
    s = _series(300, 3, [PeriodicJointError(3, 11, 2e-4)])
    estimate = ("link_length", "joint_map")
    f = pf.fit_poses(s, estimate=estimate, block_sigma=NOISE)
    lin = pf.linearise(
        f.theta, pf._data(f.z0, f.x0, s, pf._weights(s, NOISE), False), pf.regions(s)
    )
    assert lin.n_regions >= 5
    lam = pf.map_prior_of(estimate).dense(f.theta.size)
    got = cv.RegionSystems(lin, lam, f.free).steps(f.free)
    h, b = cv.posterior(lin, lam)
    idx = np.flatnonzero(f.free)
    for g in range(lin.n_regions + 1):
        hg = h - (lin.h_g[g] if g < lin.n_regions else 0.0)
        bg = b - (lin.b_g[g] if g < lin.n_regions else 0.0)
        want = np.zeros_like(got[g])
        want[idx] = np.linalg.solve(hg[np.ix_(idx, idx)], bg[idx])
        np.testing.assert_allclose(got[g], want, rtol=1e-6, atol=1e-9 * abs(want).max())


@pytest.mark.parametrize("estimate", [("link_length",), ("link_length", "joint_map")])
def test_one_step_cross_validation_equals_a_refit_without_the_region(estimate):
    """The held-out errors of a region by one Gauss–Newton step from the fit equal those
    of a fit of the other regions (its own start, identifiability and knots) to 1e-3."""
    s = _series(400, 2, [PeriodicJointError(3, 11, 2e-4)])
    f = pf.fit_poses(s, estimate=estimate, block_sigma=NOISE)
    prior = pf.map_prior_of(estimate)
    d = pf._data(f.z0, f.x0, s, pf._weights(s, NOISE), False, prior)
    label = pf.regions(s)
    lin = pf.linearise(f.theta, d, label)
    steps = cv.region_steps(lin, f.free, prior.dense(f.theta.size) if prior.size else None)
    pos, ang = cv.held_out(lin, steps)
    g = int(np.argmax(np.bincount(label)))
    train, test = s.subset(np.flatnonzero(label != g)), s.subset(np.flatnonzero(label == g))
    fg = pf.fit_poses(train, estimate=estimate, block_sigma=NOISE)
    p_ref, a_ref = pf.pose_errors(fg.predict(test), test.measured)
    np.testing.assert_allclose(pos[label == g], p_ref, rtol=1e-3, atol=1e-7)
    np.testing.assert_allclose(ang[label == g], a_ref, rtol=1e-3, atol=1e-7)


#: smooth encoder errors of the shoulder and the elbow that no estimated effect models
SMOOTH_HIDDEN = (PeriodicJointError(2, 1, 3e-4, 0.7), PeriodicJointError(3, 2, 2e-4, 0.3))


def _coverage(hidden, seeds=range(100, 108)):
    """Per seed (300 poses each), a fit of the offsets and lengths: whether a model-error
    field was found, and which effect parameters lie within 2 quoted and 2 Gauss–Newton
    σ of the truth (zero: the robot is the nominal UR10)."""
    out = []
    for seed in seeds:
        f = pf.fit_poses(
            _series(300, seed, hidden), estimate=("link_length", "joint_offset"), block_sigma=NOISE
        )
        i = np.flatnonzero(f.free[12:]) + 12
        found = any(k > 0 for k in f.robust_terms["model_error"]["ratios"])
        v = np.abs(f.theta[i])
        out.append((found, v <= 2 * f.sigma[i], v <= 2 * f.sigma_model[i], f, i))
    return out


@pytest.mark.slow
def test_the_model_error_field_of_a_pose_fit_is_absent_where_the_model_is_right():
    """Noise only: a field is found in at most 1 of 8 fits (1 % false rate per fit: 2 or
    more has probability 0.3 %; measured 0), and where none is, its σ are the
    Gauss–Newton σ."""
    res = _coverage(())
    assert sum(r[0] for r in res) <= 1
    for found, _, _, f, i in res:
        if not found:
            np.testing.assert_allclose(f.robust_terms["field"][i], f.sigma_model[i], rtol=1e-9)


@pytest.mark.slow
def test_with_a_smooth_unmodelled_joint_error_the_quoted_sigma_cover_the_truth():
    """Encoder errors of joints 2 and 3 of once and twice per turn, 0.2–0.3 mrad, left
    out of a fit of the offsets and lengths: over 8 designs the field is found in every
    fit and the quoted σ cover the truth in ≥ 85 % of the parameters (measured 91 %;
    95 % expected), the Gauss–Newton σ in < 75 % (measured 61 %)."""
    res = _coverage(SMOOTH_HIDDEN)
    assert all(r[0] for r in res)
    quoted = np.mean([r[1] for r in res])
    classic = np.mean([r[2] for r in res])
    assert quoted >= 0.85 and classic < 0.75, (quoted, classic)
