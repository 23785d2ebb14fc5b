"""The covariance under a model-error field against the spread of the estimates over
Monte-Carlo draws of that field (exact Gaussian-process draws), its absence where the
residual is white noise, and its parts against direct formulas (the likelihood's
gradient against finite differences, the sandwich against dense algebra, the acceptance
threshold against its closed form)."""

import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from robtraj.estimate import _model_error as me, field_covariance

N, SEEDS = 300, 100
#: 30 correlation lengths of the field (ℓ = 1)
X = np.linspace(0.0, 30.0, N)[:, None]
#: a line and a wave: columns a smooth model error partly looks like
A = np.c_[np.ones(N), X[:, 0] / 30, np.sin(0.7 * X[:, 0])]
THETA = np.array([0.3, -1.0, 0.5])


def _fits(field_var: float, length: float = 1.0):
    """Per seed: the least-squares estimate, its Gauss–Newton σ and its field σ, for
    y = Aθ + f(x) + ε, f a squared-exponential field of variance `field_var`, ε ~ N(0, 1)."""
    k = field_var * np.exp(-0.5 * (X - X.T) ** 2 / length**2) + 1e-9 * np.eye(N)
    chol = np.linalg.cholesky(k) if field_var else None
    h = A.T @ A
    hinv = np.linalg.inv(h)
    est, gn, fld, found = [], [], [], []
    for seed in range(SEEDS):
        rng = np.random.default_rng(seed)
        y = A @ THETA + rng.normal(size=N)
        if chol is not None:
            y = y + chol @ rng.normal(size=N)
        theta = scipy.linalg.lstsq(A, y)[0]
        e = y - A @ theta
        s2 = e @ e / (N - A.shape[1])
        f = field_covariance(h, [A], e[None], X, np.ones(N))
        est.append(theta)
        gn.append(np.sqrt(s2 * np.diag(hinv)))
        fld.append(np.sqrt(s2 * np.diag(f.covariance)))
        found.append(f.found)
    return np.array(est), np.array(gn), np.array(fld), np.array(found)


@pytest.mark.slow
def test_with_a_smooth_model_error_the_field_sigma_covers_the_estimates_spread():
    """A field of 4× the white variance over 30 of its correlation lengths: over 100
    draws |θ̂ − θ| ≤ 2σ in ≥ 90 % of them (95 % expected), where the Gauss–Newton σ cover
    < 60 %; the field σ's RMS is 0.8–1.5 times the estimates' spread (each draw's σ rest
    on its own estimate of the variances, one realisation of the field)."""
    est, gn, fld, found = _fits(4.0)
    err = est - THETA
    spread = np.sqrt(np.mean(err**2, 0))
    quoted = np.sqrt(np.mean(fld**2, 0))
    assert np.all((quoted / spread > 0.8) & (quoted / spread < 1.5)), quoted / spread
    assert np.mean(np.abs(err) <= 2 * fld) >= 0.90, np.mean(np.abs(err) <= 2 * fld, 0)
    assert np.mean(np.abs(err) <= 2 * gn) < 0.60, np.mean(np.abs(err) <= 2 * gn, 0)
    assert np.mean(found) > 0.95


@pytest.mark.slow
def test_where_the_residual_is_white_noise_the_field_sigma_is_the_gauss_newton_one():
    """No field: none is accepted in ≥ 95 % of 100 draws (the test's false rate is 1 %:
    more than 5 of 100 has probability 0.0005 under it), and where none is the
    covariance is exactly ``s²H⁻¹``; the field σ are within 20 % of the Gauss–Newton σ in
    ≥ 95 % of the draws."""
    est, gn, fld, found = _fits(0.0)
    assert np.mean(~found) >= 0.95, np.mean(~found)
    np.testing.assert_allclose(fld[~found], gn[~found], rtol=1e-9)
    close = np.all(np.abs(fld / gn - 1) <= 0.2, 1)
    assert np.mean(close) >= 0.95, np.mean(close)


def _problem(seed=0, n=120, c=2, p=3):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 3, (n, 2))
    rows = [rng.normal(size=(n, p)) for _ in range(c)]
    res = [rng.normal(size=n) + np.sin(2 * x[:, 0]) for _ in range(c)]
    amp = rng.uniform(0.5, 1.5, n)
    return rows, res, x, amp


def test_the_restricted_likelihood_gradient_is_its_finite_difference():
    rows, res, x, amp = _problem()
    reml = me._Reml(rows, res, x, amp, (0.3, 1.0, 3.0))
    z = np.array([-1.0, 0.5, -2.0])
    (_, _), g = reml(z)
    for j in range(3):
        dz = np.zeros(3)
        dz[j] = 1e-5
        fd = (reml(z + dz, grad=False)[0] - reml(z - dz, grad=False)[0]) / 2e-5
        np.testing.assert_allclose(g[j], fd, rtol=1e-5, atol=1e-6)


def test_the_restricted_likelihood_is_the_direct_formula():
    """−2 log L_R against dense algebra over the stacked components: (N − p) log Q +
    log|V_all| + log|AᵀV_all⁻¹A| with Q the generalised residual cost."""
    rows, res, x, amp = _problem(1)
    lengths = (0.3, 1.0)
    kappa = np.array([0.7, 2.0])
    reml = me._Reml(rows, res, x, amp, lengths)
    val, q = reml(np.log(kappa), grad=False)
    d2 = np.sum((x[:, None] - x[None]) ** 2, -1)
    k = sum(kk * np.exp(-d2 / (2 * ell**2)) for kk, ell in zip(kappa, lengths))
    v = np.eye(len(x)) + np.outer(amp, amp) * k
    v_all = scipy.linalg.block_diag(v, v)
    a_all = np.concatenate(rows)
    y_all = np.concatenate(res)
    vi = np.linalg.inv(v_all)
    m = a_all.T @ vi @ a_all
    beta = np.linalg.solve(m, a_all.T @ vi @ y_all)
    r = y_all - a_all @ beta
    q_want = r @ vi @ r
    want = (len(y_all) - 3) * np.log(q_want) + np.linalg.slogdet(v_all)[1] + np.linalg.slogdet(m)[1]
    np.testing.assert_allclose(q, q_want, rtol=1e-10)
    np.testing.assert_allclose(val, want, rtol=1e-10)


def test_the_sandwich_is_the_dense_formula(monkeypatch):
    """The covariance of the flat parameters under the fitted field, formed in row blocks,
    against ``w·[H⁻¹(H + Σ_c A_cᵀ D K D A_c)H⁻¹]_ff`` with the dense kernel."""
    monkeypatch.setattr(me, "_BLOCK", 37)
    rows, res, x, amp = _problem(2, p=4)
    h = sum(r.T @ r for r in rows) + np.diag([0, 0, 0, 5.0])
    res = [e + 3 * np.sin(1.5 * x[:, 1]) for e in res]
    flat = np.array([True, True, True, False])
    f = field_covariance(h, rows, np.array(res), x, amp, flat, lengths=(0.3, 1.0))
    assert f.found
    d2 = np.sum((x[:, None] - x[None]) ** 2, -1)
    k = sum(kk * np.exp(-d2 / (2 * ell**2)) for kk, ell in zip(f.ratios, f.lengths))
    dkd = np.outer(amp, amp) * k
    hinv = np.linalg.inv(h)
    full = hinv @ (h + sum(r.T @ dkd @ r for r in rows)) @ hinv
    np.testing.assert_allclose(f.covariance, f.white * full[np.ix_(flat, flat)], rtol=1e-9)


def test_the_acceptance_threshold_of_one_variance_is_the_boundary_chi2():
    """One variance on its boundary: ½χ²₀ + ½χ²₁, whose 1 % point is χ²₁'s 2 % point."""
    assert me.field_threshold(1) == pytest.approx(scipy.stats.chi2.isf(0.02, 1), rel=1e-6)
    assert me.field_threshold(4) > me.field_threshold(1)
