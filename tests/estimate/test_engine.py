"""The one least-squares engine (`robtraj.estimate.solve`) against independent references:
linear least squares (NumPy), a nonlinear fit (scipy), the chunked bundle normal
equations against automatic differentiation of the pure residual function."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares

from robtraj import UserError
from robtraj.estimate import covariance, gauss_newton_step, identifiability, normal_at, solve


def _linear_normal(theta, data):
    a, y, sw = data
    r = sw * (y - a @ theta)
    j = sw[:, None] * a
    return j.T @ j, j.T @ r, r @ r


def _exp_residual(theta, t, y):
    return y - theta[0] * jnp.exp(-theta[1] * t) - theta[2]


def _exp_normal(theta, data):
    t, y = data
    r = _exp_residual(theta, t, y)
    j = -jax.jacfwd(_exp_residual)(theta, t, y)  # Jacobian of the prediction
    return j.T @ j, j.T @ r, r @ r


@pytest.fixture(scope="module")
def linear():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(40, 4)) * np.array([1.0, 1e3, 1e-3, 5.0])  # badly scaled columns
    y = a @ np.array([0.3, -2e-3, 400.0, 1.0]) + rng.normal(0, 0.1, 40)
    sw = rng.uniform(0.5, 2.0, 40)
    return jnp.asarray(a), jnp.asarray(y), jnp.asarray(sw)


def test_linear_least_squares_matches_numpy(linear):
    a, y, sw = (np.asarray(x) for x in linear)
    sol = solve(_linear_normal, linear, np.zeros(4), np.ones(4, bool), n_residuals=40)
    ref = np.linalg.lstsq(sw[:, None] * a, sw * y, rcond=None)[0]
    assert sol.converged, sol.reason
    np.testing.assert_allclose(sol.theta, ref, rtol=1e-9)
    np.testing.assert_allclose(sol.cost, np.sum((sw * (y - a @ ref)) ** 2), rtol=1e-9)


def test_fixed_parameters_stay_and_the_rest_is_the_reduced_optimum(linear):
    a, y, sw = (np.asarray(x) for x in linear)
    theta0 = np.array([0.0, 0.0, 123.0, 0.0])
    free = np.array([True, True, False, True])
    sol = solve(_linear_normal, linear, theta0, free)
    ref = np.linalg.lstsq((sw[:, None] * a)[:, free], sw * (y - a[:, 2] * 123.0), rcond=None)[0]
    assert sol.theta[2] == 123.0
    np.testing.assert_allclose(sol.theta[free], ref, rtol=1e-9)


def test_one_gauss_newton_step_solves_a_linear_problem_and_keeps_fixed_entries(linear):
    a, y, sw = (np.asarray(x) for x in linear)
    theta0 = np.array([1.0, 0.0, 123.0, -2.0])
    free = np.array([True, True, False, True])
    sol = gauss_newton_step(theta0, free, normal_at(_linear_normal, theta0, linear))
    ref = np.linalg.lstsq((sw[:, None] * a)[:, free], sw * (y - a[:, 2] * 123.0), rcond=None)[0]
    assert sol.theta[2] == 123.0 and sol.converged and sol.steps == 1
    np.testing.assert_allclose(sol.theta[free], ref, rtol=1e-9)
    # the predicted cost is the cost there (the problem is linear)
    np.testing.assert_allclose(sol.cost, np.sum((sw * (y - a @ sol.theta)) ** 2), rtol=1e-9)


def test_one_step_from_the_whole_optimum_reaches_the_optimum_of_a_part():
    """Second order: from the optimum on every point, one step on half of them lands on
    their optimum (scipy) with an error of second order in the move (|move|² here)."""
    rng = np.random.default_rng(1)
    t = np.linspace(0, 4, 60)
    y = 2.0 * np.exp(-1.3 * t) + 0.5 + rng.normal(0, 0.01, t.size)
    whole = least_squares(lambda p: np.asarray(_exp_residual(jnp.asarray(p), t, y)),
                          np.array([1.0, 0.5, 0.0]), xtol=1e-14).x  # fmt: skip
    half = t < 2.0
    part = least_squares(lambda p: np.asarray(_exp_residual(jnp.asarray(p), t[half], y[half])),
                         whole, xtol=1e-14).x  # fmt: skip
    data = (jnp.asarray(t[half]), jnp.asarray(y[half]))
    sol = gauss_newton_step(whole, np.ones(3, bool), normal_at(_exp_normal, whole, data))
    move = np.max(np.abs(part - whole))
    assert move > 1e-3  # half the points do move the optimum
    assert np.max(np.abs(sol.theta - part)) < move**2


def test_nonlinear_fit_matches_scipy_and_any_optimistix_solver_runs():
    rng = np.random.default_rng(1)
    t = np.linspace(0, 4, 60)
    y = 2.0 * np.exp(-1.3 * t) + 0.5 + rng.normal(0, 0.01, t.size)
    data = (jnp.asarray(t), jnp.asarray(y))
    x0 = np.array([1.0, 0.5, 0.0])
    ref = least_squares(lambda p: np.asarray(_exp_residual(jnp.asarray(p), *data)), x0, xtol=1e-14)
    for solver in (None, optx.GaussNewton(rtol=1e-10, atol=1e-12), optx.Dogleg(1e-10, 1e-12)):
        sol = solve(_exp_normal, data, x0, np.ones(3, bool), solver=solver)
        assert sol.converged, (solver, sol.reason)
        np.testing.assert_allclose(sol.theta, ref.x, rtol=1e-7, atol=1e-9)


def test_stopping_early_is_not_convergence():
    t = np.linspace(0, 4, 60)
    data = (jnp.asarray(t), jnp.asarray(2.0 * np.exp(-1.3 * t) + 0.5))
    sol = solve(_exp_normal, data, np.array([1.0, 0.5, 0.0]), np.ones(3, bool), max_steps=2)
    assert not sol.converged and "2 steps" in sol.reason


@pytest.mark.parametrize(
    "case, message",
    [("few", "2 residuals for 3 free parameters"), ("nan", "not finite")],
)
def test_bad_input_is_a_one_line_user_error(case, message):
    t = np.linspace(0, 1, 2 if case == "few" else 10)
    y = np.where(np.arange(t.size) == 1, np.nan if case == "nan" else 0.0, 1.0)
    with pytest.raises(UserError, match=message) as e:
        solve(
            _exp_normal,
            (jnp.asarray(t), jnp.asarray(y)),
            np.ones(3),
            np.ones(3, bool),
            n_residuals=t.size,
        )
    assert "\n" not in str(e.value)


def test_identifiability_names_an_exact_null_direction_and_covariance_excludes_it():
    rng = np.random.default_rng(2)
    j = rng.normal(size=(30, 3))
    j = np.column_stack([j, 2.0 * j[:, 0] - 3.0 * j[:, 1]])  # column 3 = 2·c0 − 3·c1
    h = j.T @ j
    names = ["a", "b", "c", "d"]
    droppable = np.array([False, False, False, True])
    free, rep = identifiability(h, names, np.ones(4, bool), droppable)
    assert list(free) == [True, True, True, False]
    assert rep["dropped"] == [{"parameter": "d", "confounded_with": ["b", "a"]}]
    assert rep["undetermined"] == []
    cov, rank = covariance(h, free, 2.0)
    assert rank == 3 and np.all(cov[3] == 0)
    np.testing.assert_allclose(cov[:3, :3], 2.0 * np.linalg.inv(h[:3, :3]), rtol=1e-8)


@pytest.mark.parametrize(
    "terms",
    [pytest.param("library", marks=pytest.mark.exhaustive), "dictionary", "rigid LEDs"],
)
def test_bundle_normal_equations_are_those_of_the_pure_residuals(terms):
    """Chunk-accumulated ``JᵀJ``, ``Jᵀr`` at a θ away from the current values (where the
    SE3 corrections need their right Jacobian), with every effect free and non-zero (the
    library's and every term of the dictionary; the library alone runs on demand), equal
    those of `residuals` through `jax.jacfwd` over all frames at once. "rigid LEDs": the
    LED-level effects at zero, whose columns the rigid path takes in closed form."""
    from robtraj.estimate import calibration as cal
    from robtraj.estimate._calib_parameters import effect_of
    from robtraj.estimate._calib_problem import is_led_level
    from robtraj.estimate._calib_setup import setup
    from robtraj.model import EFFECT_NAMES, dictionary
    from robtraj.sim import simulate

    rec = simulate("paper", seed=0, duration=8.0, rate=25.0)
    # every effect free: the closed-form effect columns of the tool pose are checked too
    names = EFFECT_NAMES + (dictionary(6) if terms != "library" else ())
    rigid = terms == "rigid LEDs"
    st = setup(rec, names, None, None, 16, lambda _m: None, start_only=rigid)
    assert st.bundle.problem.rigid_leds == rigid
    rng = np.random.default_rng(3)
    theta = np.zeros(len(st.names_theta))
    theta[:12] = rng.normal(0, 2e-3, 12)
    theta[12 : st.q] = rng.normal(0, 1e-4, st.q - 12)
    compliance = [i for i, n in enumerate(st.names_theta) if n.startswith("joint_compliance")]
    theta[compliance] = rng.normal(0, 1e-6, len(compliance))  # [rad/(N·m)]
    squared = [i for i, n in enumerate(st.names_theta) if "torque_squared" in n]
    theta[squared] = rng.normal(0, 1e-8, len(squared))  # [rad/(N·m)²]
    theta[st.q :] = rng.normal(0, 1e-4, theta.size - st.q) * st.has_column[st.q :]
    if rigid:
        led = [i for i, n in enumerate(st.names_theta[: st.q]) if is_led_level(effect_of(n))]
        assert len(led) >= 8  # led_angle_bias, tracker_scale and the dictionary's LED terms
        theta[led] = 0.0
    theta = jnp.asarray(theta)
    h, b, c = normal_at(cal.bundle_normal, theta, st.bundle)  # compiled by `setup`
    r = eqx.filter_jit(cal.residuals)(theta, st.bundle)
    j = -eqx.filter_jit(jax.jacfwd(cal.residuals))(theta, st.bundle)
    np.testing.assert_allclose(c, r @ r, rtol=1e-10)
    scale = np.sqrt(np.diag(np.asarray(j.T @ j)))
    # padding columns of the constellation basis, and the compliance of a joint that
    # carries no gravity torque (its column is rounding noise): compared unscaled
    scale = np.where(scale > 1e-9 * np.median(scale), scale, 1.0)
    np.testing.assert_allclose(
        np.asarray(h) / np.outer(scale, scale),
        np.asarray(j.T @ j) / np.outer(scale, scale),
        atol=1e-9,
    )
    np.testing.assert_allclose(
        np.asarray(b) / scale, np.asarray(j.T @ r) / scale, atol=1e-9 * np.sqrt(float(c))
    )


def test_a_null_direction_of_parameters_that_cannot_be_fixed_is_named_undetermined():
    """Two translations that enter the data only through their sum (camera←base and
    flange←tool of a constant-orientation run) are reported as undetermined."""
    rng = np.random.default_rng(4)
    j = rng.normal(size=(40, 3))
    j = np.column_stack([j[:, 0], j[:, 0], j[:, 1], j[:, 2]])  # columns 0 and 1 confounded
    h = j.T @ j
    names = ["camera_from_base.tx", "flange_from_tool.tx", "b", "c"]
    free, rep = identifiability(h, names, np.ones(4, bool), np.zeros(4, bool))
    assert list(free) == [True] * 4 and rep["dropped"] == []
    assert rep["undetermined"] == ["camera_from_base.tx", "flange_from_tool.tx"]


def test_bundle_normal_equations_with_a_joint_map_add_its_prior():
    """A joint angle error map estimated: its columns (dense hat features) are those of
    `residuals` through `jax.jacfwd`, and the normal equations add the term's prior,
    ``H + Λ``, ``b − Λc``, ``cost + cᵀΛc``, on its entries only."""
    from robtraj.estimate import calibration as cal
    from robtraj.estimate._calib_setup import setup
    from robtraj.model import term
    from robtraj.sim import simulate

    rec = simulate("paper", seed=0, duration=8.0, rate=25.0)
    st = setup(rec, ("joint_offset", "joint2_map"), None, None, 16, lambda _m: None)
    mine = [i for i, n in enumerate(st.names_theta) if n.startswith("joint2_map.")]
    assert len(mine) == term("joint2_map").size
    np.testing.assert_array_equal(np.asarray(st.bundle.prior.index), mine)
    rng = np.random.default_rng(4)
    theta = np.zeros(len(st.names_theta))
    theta[: st.q] = rng.normal(0, 1e-4, st.q)
    theta = jnp.asarray(theta)
    h, b, c = normal_at(cal.bundle_normal, theta, st.bundle)
    r = eqx.filter_jit(cal.residuals)(theta, st.bundle)
    j = -eqx.filter_jit(jax.jacfwd(cal.residuals))(theta, st.bundle)
    lam = st.bundle.prior.dense(theta.size)
    t = np.asarray(theta)
    np.testing.assert_allclose(c, r @ r + t @ lam @ t, rtol=1e-10)
    want_h = np.asarray(j.T @ j) + lam
    scale = np.sqrt(np.diag(want_h))
    scale = np.where(scale > 1e-9 * np.median(scale), scale, 1.0)
    np.testing.assert_allclose(
        np.asarray(h) / np.outer(scale, scale), want_h / np.outer(scale, scale), atol=1e-9
    )
    np.testing.assert_allclose(
        np.asarray(b) / scale,
        (np.asarray(j.T @ r) - lam @ t) / scale,
        atol=1e-9 * np.sqrt(float(c)),
    )


def _ridge_normal(theta, data):
    a, y, sw, prior = data
    h, b, c = _linear_normal(theta, (a, y, sw))
    return prior.add_to(h, b, c, theta[prior.index])


def test_a_gaussian_prior_gives_the_closed_form_map_estimate_and_posterior(linear):
    """Linear least squares with a zero-mean Gaussian prior on two entries: the engine's
    optimum is the MAP (ridge) solution ``(AᵀWA + Λ)⁻¹AᵀWy`` and its covariance
    ``(AᵀWA + Λ)⁻¹``; a column the data cannot tell apart from another is determined
    by the prior (identifiability keeps it)."""
    from robtraj.estimate import GaussianPrior

    a, y, sw = (np.asarray(x) for x in linear)
    a = np.concatenate([a, a[:, 1:2]], 1)  # entry 4 duplicates entry 1: a null direction
    lam = np.array([[4e4, 1e4], [1e4, 9e4]])
    prior = GaussianPrior(jnp.asarray([1, 4]), jnp.asarray(lam))
    data = (jnp.asarray(a), jnp.asarray(y), jnp.asarray(sw), prior)
    free = np.ones(5, bool)
    sol = solve(_ridge_normal, data, np.zeros(5), free, n_residuals=40)
    full = prior.dense(5)
    aw = sw[:, None] * a
    post = aw.T @ aw + full
    ref = np.linalg.solve(post, aw.T @ (sw * y))
    assert sol.converged, sol.reason
    np.testing.assert_allclose(sol.theta, ref, rtol=1e-8)
    np.testing.assert_allclose(
        sol.cost, np.sum((sw * (y - a @ ref)) ** 2) + ref @ full @ ref, rtol=1e-9
    )
    h = np.asarray(normal_at(_ridge_normal, jnp.asarray(sol.theta), data)[0])
    names = ["a", "b", "c", "d", "e"]
    kept, rep = identifiability(h, names, free, np.ones(5, bool))
    assert kept.all() and not rep["dropped"] and not rep["undetermined"]
    cov, rank = covariance(h, free)
    assert rank == 5
    np.testing.assert_allclose(cov, np.linalg.inv(post), rtol=1e-7)
    # without the prior the duplicate is a null direction
    h0 = aw.T @ aw
    kept0, rep0 = identifiability(h0, names, free, np.ones(5, bool))
    assert rep0["dropped"] and not kept0.all()


@pytest.mark.parametrize("deficient", [False, True])
def test_the_square_root_form_reproduces_the_normal_equations(deficient):
    """The solver's residual and Jacobian: ``JᵀJ = Hs``, ``Jᵀr = −bs`` and ``|r|²`` the
    cost, by the Cholesky factor (full rank) or by the eigendecomposition with the null
    direction dropped (rank-deficient: an exact copy of a column)."""
    from robtraj.estimate._solve import LeastSquares, _compressed

    rng = np.random.default_rng(3)
    a = rng.normal(size=(30, 6)) * np.array([1.0, 1e3, 1e-3, 5.0, 1.0, 2.0])
    if deficient:
        a[:, 5] = 2.0 * a[:, 4]
    r0 = rng.normal(size=30)
    h, b, cost = a.T @ a, a.T @ r0, float(r0 @ r0)
    scale = np.sqrt(np.diag(h))
    problem = LeastSquares(*(jnp.asarray(x) for x in (np.zeros(6), h, b, cost, scale, np.ones(6))))
    res, jac = (np.asarray(x) for x in _compressed(jnp.zeros(6), problem))
    hs, bs = h / np.outer(scale, scale), b / scale
    # rank-deficient: the null direction n leaves the Hessian and the gradient (bs ⟂ n)
    np.testing.assert_allclose(jac.T @ jac, hs, atol=1e-10)
    np.testing.assert_allclose(jac.T @ res, -bs, atol=1e-10)
    np.testing.assert_allclose(res @ res, cost, rtol=1e-10)
    assert np.linalg.matrix_rank(jac, tol=1e-8) == (5 if deficient else 6)


def test_the_solution_carries_the_normal_equations_at_the_estimate():
    t = np.linspace(0, 4, 60)
    y = 2.0 * np.exp(-1.3 * t) + 0.5 + np.random.default_rng(1).normal(0, 0.01, t.size)
    data = (jnp.asarray(t), jnp.asarray(y))
    sol = solve(_exp_normal, data, np.array([1.0, 0.5, 0.0]), np.ones(3, bool))
    assert sol.converged and sol.normal is not None
    ref = normal_at(_exp_normal, jnp.asarray(sol.theta), data)
    for got, want in zip(sol.normal, ref):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


@pytest.mark.parametrize("log_cond", [2.0, 8.0, 11.0])
def test_covariance_is_the_eigen_pseudo_inverse_whatever_route_it_takes(log_cond, monkeypatch):
    """`covariance` inverts a well-conditioned scaled matrix by Cholesky and falls back
    to the eigendecomposition toward `RCOND`: on matrices whose smallest eigenvalue is
    10^-log_cond (10²: Cholesky; 10⁸: the eigendecomposition, everything kept; 10¹¹:
    beyond 1/RCOND, one direction left out) it equals the pseudo-inverse built from
    the spectrum."""
    from robtraj.estimate import RCOND

    calls = []
    eigh = np.linalg.eigh
    monkeypatch.setattr(np.linalg, "eigh", lambda a: calls.append(1) or eigh(a))
    rng = np.random.default_rng(4)
    p = 40
    v, _ = np.linalg.qr(rng.normal(size=(p, p)))
    lam = np.logspace(0.0, -1.0, p)
    lam[-1] = 10.0**-log_cond
    d = rng.uniform(0.1, 10.0, p)
    h = (v * lam) @ v.T * np.outer(d, d)
    # the covariance sees the matrix scaled to a unit diagonal
    e = np.sqrt(np.diag(h))
    lam_s, v_s = eigh(h / np.outer(e, e))
    keep = lam_s > RCOND * lam_s[-1]
    want = (v_s[:, keep] / lam_s[keep]) @ v_s[:, keep].T / np.outer(e, e)
    cov, rank = covariance(h, np.ones(p, bool))
    assert len(calls) == (0 if log_cond < 5 else 1)
    assert rank == keep.sum() == (p - 1 if log_cond > 10 else p)
    np.testing.assert_allclose(cov, want, rtol=1e-9, atol=1e-12 * abs(want).max())


def test_a_composed_normal_function_runs_its_own_kernels_with_the_same_solution():
    """A normal function marked `composed` is called as it is on every evaluation (its
    Python runs each time, its kernels are its own), and the solve is that of the same
    function compiled whole."""
    from robtraj.estimate import composed

    calls = []
    residual = jax.jit(_exp_residual)
    jacobian = jax.jit(jax.jacfwd(_exp_residual))

    @composed
    def normal(theta, data):
        calls.append(1)
        t, y = data
        r, j = residual(theta, t, y), -jacobian(theta, t, y)
        return j.T @ j, j.T @ r, r @ r

    t = np.linspace(0, 4, 60)
    y = 2.0 * np.exp(-1.3 * t) + 0.5 + np.random.default_rng(1).normal(0, 0.01, t.size)
    data = (jnp.asarray(t), jnp.asarray(y))
    start = np.array([1.0, 0.5, 0.0])
    got = solve(normal, data, start, np.ones(3, bool))
    want = solve(_exp_normal, data, start, np.ones(3, bool))
    assert got.converged and len(calls) == got.steps  # the start and every step but the last
    np.testing.assert_allclose(got.theta, want.theta, rtol=1e-10)
    for a, b in zip(normal_at(normal, jnp.asarray(start), data), _exp_normal(start, data)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)
