"""The one least-squares engine: Optimistix on chunk-accumulated normal equations.

A problem is given by its normal equations, a pure function
``normal(theta, data) -> (H, b, cost)`` with ``cost = Σ w r²`` (the weighted residual
sum of squares of every observation), ``b = JᵀW r`` (so ``∇cost = −2b``) and
``H = JᵀWJ``, accumulated however the observation kind likes (chunks of frames for whole
recordings, the Jacobian of a few thousand poses at once). The Jacobian of the
observations is never handed to the solver.

The solver sees the *square-root information form* of the problem: with the column-scaled
normal matrix ``Hs = VΛVᵀ`` (eigenvalues below `RCOND`·λ_max dropped), the residual

    R(z) = [ −Λ^{-½} Vᵀ bs ,  sqrt(cost − bsᵀ Hs⁺ bs) ]       (p + 1 entries)

with the declared Jacobian ``[Λ^{½} Vᵀ; 0]`` has ``|R|² = cost``, ``JᵀR = −bs`` (the exact
gradient) and ``JᵀJ = Hs`` (the Gauss–Newton Hessian): any Optimistix least-squares
solver (default: `optx.LevenbergMarquardt`'s damped Newton descent in `TrustRegion`, a
classical trust region aware of the cost's rounding) then runs exactly its algorithm on
the full problem, one pass over the observations per step, with linear algebra of the
parameter count only.

Column scaling and the free-parameter selection belong to the problem: the solver's
variable is ``z = D·(θ − θ₀)`` on the free entries with D = sqrt(diag H / `DIAGONAL`) at
the start (z is in units of 1000 conditional standard errors when the weights are inverse
variances); fixed entries stay at θ₀.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from .._errors import UserError
from ._uncertainty import RCOND, column_scale, covariance

#: diagonal of the scaled normal matrix: Optimistix's trust region starts at damping
#: λ = 1, i.e. 1/`DIAGONAL` of the diagonal (close to Gauss–Newton: the closed-form start
#: is near the optimum; a rejected step raises the damping)
DIAGONAL = 1e6
#: termination: a step below `ATOL` in z (max norm; 1e-3 of a conditional standard error
#: for inverse-variance weights — the next Gauss–Newton step is smaller still) together
#: with a cost change below `ATOL` + `RTOL`·cost
ATOL = 1e-3 / DIAGONAL**0.5
RTOL = 1e-8
#: relative rounding level of a cost summed over a whole recording: a step whose predicted
#: and actual changes are both below it cannot be told from the optimum by the cost
ROUNDING = 1e-12


class LeastSquares(eqx.Module):
    """The solver's view of a problem at one point ``z`` (the ``args`` of `_residual`):
    the normal equations of the free parameters there (padded to a fixed size `n`),
    the column scale and the free mask (0 on the padding)."""

    z: Float[Array, " n"]  # where `h`, `b`, `cost` were evaluated
    h: Float[Array, "n n"]
    b: Float[Array, " n"]
    cost: Float[Array, ""]
    scale: Float[Array, " n"]  # column scale D
    free: Float[Array, " n"]  # 1 free, 0 padding


class _Free(eqx.Module):
    """Where the solver's variable sits in θ: ``θ = θ₀ + scatter(index, free·z/scale)``."""

    theta0: Float[Array, " p"]
    index: Int[Array, " n"]  # θ entry of each entry of z (padding: entry 0, weight 0)

    def theta(self, problem: LeastSquares, z: Float[Array, " n"]) -> Float[Array, " p"]:
        return self.theta0.at[self.index].add(problem.free * z / problem.scale)


@jax.jit
def _restrict(h, b, index):
    """The free block of the normal equations (rows and columns `index`)."""
    return h[index[:, None], index[None, :]], b[index]


def padded_size(n_free: int) -> int:
    """The size of the solver's variable for `n_free` free parameters: rounded up (to 8
    up to 64, 32 up to 512, then 128), so that fits whose free sets differ a little
    share a compilation of the step, and one with many parameters held pays the linear
    algebra of the free ones only."""
    step = 8 if n_free <= 64 else 32 if n_free <= 512 else 128
    return max(step, -(-n_free // step) * step)


#: power and inverse iterations that estimate the scaled normal matrix's extreme
#: eigenvalues (`_square_root`)
_ITERATIONS = 12


def _square_root(hs, bs):
    """``(Jᵀ, r)`` with ``JᵀJ = hs`` and ``Jᵀr = −bs`` on the directions whose
    eigenvalue exceeds `RCOND`·λ_max (the others: zero rows of J and r).

    The Cholesky factor ``hs = LLᵀ`` gives ``J = Lᵀ``, ``r = −L⁻¹bs`` where hs is
    positive definite and no eigenvalue lies below the cut: λ_max by power iteration,
    λ_min by inverse iteration with L (each iterate's Rayleigh quotient bounds λ_min from
    above, and a near-null direction, far below the next eigenvalue, is found at once).
    Otherwise the eigendecomposition ``hs = VΛVᵀ`` gives ``J = Λ^{½}Vᵀ`` with the small
    eigenvalues dropped; only the branch taken runs."""
    p = hs.shape[0]
    low = jnp.linalg.cholesky(hs)
    start = jnp.ones(p) + jnp.arange(p) / p

    def power(_, x):
        y = hs @ x
        return y / jnp.linalg.norm(y)

    def inverse(_, x):
        y = jax.scipy.linalg.solve_triangular(low, x, lower=True)
        y = jax.scipy.linalg.solve_triangular(low.T, y, lower=False)
        return y / jnp.linalg.norm(y)

    x_max = jax.lax.fori_loop(0, _ITERATIONS, power, start / jnp.linalg.norm(start))
    x_min = jax.lax.fori_loop(0, _ITERATIONS, inverse, start / jnp.linalg.norm(start))
    lam_max, lam_min = x_max @ hs @ x_max, x_min @ hs @ x_min
    ok = jnp.all(jnp.isfinite(low)) & (lam_min > RCOND * lam_max)

    def by_cholesky(_):
        return low.T, -jax.scipy.linalg.solve_triangular(low, bs, lower=True)

    def by_eigh(_):
        lam, v = jnp.linalg.eigh(hs)
        keep = lam > RCOND * lam[-1]
        s = jnp.sqrt(jnp.where(keep, lam, 1.0))
        jt = jnp.where(keep[:, None], s[:, None] * v.T, 0.0)
        return jt, jnp.where(keep, -(v.T @ bs) / s, 0.0)

    return jax.lax.cond(ok, by_cholesky, by_eigh, None)


def _compressed(z, problem: LeastSquares):
    """Square-root information residual `(p + 1,)` and its Jacobian `(p + 1, p)` at
    `problem.z` (NaN elsewhere: the normal equations are only known there)."""
    f = problem.free / problem.scale
    # the padding entries: unit curvature and zero gradient, so that they never move
    # (a zero column would leave a Gauss–Newton step undefined)
    hs = problem.h * jnp.outer(f, f) + jnp.diag(1.0 - problem.free)
    bs = problem.b * f
    jt, r = _square_root(0.5 * (hs + hs.T), bs)
    tail = jnp.sqrt(jnp.maximum(problem.cost - r @ r, 0.0))
    res = jnp.concatenate([r, tail[None]])
    jac = jnp.concatenate([jt, jnp.zeros((1, jt.shape[1]), jt.dtype)])
    # a non-finite cost must not look like an optimum to the trust region
    res = jnp.where(jnp.isfinite(problem.cost), res, jnp.inf)
    res = jnp.where(jnp.all(z == problem.z), res, jnp.nan)
    return res, jac


@eqx.filter_custom_jvp
def _residual(z, problem):
    return _compressed(z, problem)[0]


@_residual.def_jvp
def _residual_jvp(primals, tangents):
    z, problem = primals
    dz, _ = tangents
    res, jac = _compressed(z, problem)
    return res, (jnp.zeros_like(res) if dz is None else jac @ dz)


def _fn(z, problem):
    return _residual(z, problem), None


@dataclasses.dataclass(frozen=True)
class Solution:
    """Outcome of `solve`: `theta` the estimate (NumPy), `cost` ``Σ w r²`` there,
    `converged` True only when Optimistix's termination criterion held (step and cost
    change below tolerance) on a finite cost; `reason` says why it stopped."""

    theta: np.ndarray
    cost: float
    converged: bool
    reason: str
    steps: int
    #: ``normal(theta, data)`` where the solver evaluated it at `theta` itself (None
    #: otherwise): a caller's covariance needs no further pass over the data
    normal: tuple | None = None


def gauss_newton_step(theta0, free, start: tuple) -> Solution:
    """One Gauss–Newton step from `theta0`, on the normal equations there (`start` =
    ``normal(theta0, data)``): ``θ = θ₀ + H⁺ b`` on the `free` entries (the column-scaled
    pseudo-inverse of `robtraj.estimate.covariance`, null directions left out). `cost` is
    the step's predicted ``cost − bᵀ H⁺ b``; `converged` is True by construction.

    For a problem nearly linear over the step, e.g. a refit of part of the observations
    from the optimum on all of them, this is that part's optimum to second order in the
    step, for no pass beyond the one that gave `start`."""
    h, b, cost = start
    b = np.asarray(b)
    inv, _ = covariance(np.asarray(h), np.asarray(free, bool))
    step = inv @ b
    theta = np.asarray(theta0, np.float64) + step
    return Solution(theta, float(cost) - float(b @ step), True, "one Gauss–Newton step", 1)


def normal_at(normal: Callable, theta, data):
    """``normal(theta, data)`` compiled (once per `normal` and data shape); a `composed`
    normal function is called as it is."""
    if getattr(normal, "composed", False):
        return normal(theta, data)
    return _compiled_normal(normal, theta, data)


@eqx.filter_jit
def _compiled_normal(normal: Callable, theta, data):
    return normal(theta, data)


def composed(normal: Callable) -> Callable:
    """Mark `normal` as composed of compiled kernels of its own, which `normal_at` calls
    as it is instead of compiling the whole: a kernel it shares with other functions
    (the Jacobian of the observations, say) then compiles once for all of them. It must
    still be jit-compatible."""
    normal.composed = True
    return normal


def compile_normal(ahead, normal: Callable, theta, data):
    """Compile `normal_at`'s kernel for `normal` and these shapes on `ahead`'s background
    thread (a `robtraj.estimate._compile_ahead.CompileAhead`; a `composed` normal compiles
    its own kernels when first called); returns the future."""
    if getattr(normal, "composed", False):
        return ahead.run(lambda: None)
    return ahead.submit(_compiled_normal, normal, theta, data)


def _initial_state(solver, p: int):
    """Optimistix's initial state for `p` parameters, shared by every solve of that size
    and solver (its static parts are compared by identity: one compilation of `_step`)."""
    try:
        return _shared_initial_state(solver, p)
    except TypeError:  # a solver with array fields is not hashable: no sharing
        return _new_initial_state(solver, p)


def _new_initial_state(solver, p: int):
    y = jnp.zeros(p)
    return solver.init(
        _fn, y, _placeholder(p), {}, jax.ShapeDtypeStruct((p + 1,), y.dtype), None, frozenset()
    )


_shared_initial_state = functools.lru_cache(maxsize=64)(_new_initial_state)


def _placeholder(p: int) -> LeastSquares:
    z = jnp.zeros(p)
    return LeastSquares(z, jnp.eye(p), z, jnp.zeros(()), jnp.ones(p), jnp.ones(p))


def compile_steps(ahead, solver: optx.AbstractLeastSquaresSolver, p: int):
    """Compile `solve`'s step for `solver` and `p` parameters on `ahead`'s background
    thread (a `robtraj.estimate._compile_ahead.CompileAhead`); returns its future."""

    def compile_step():
        state = _initial_state(solver, p)
        _step.lower(solver, jnp.zeros(p), _placeholder(p), state).compile()

    return ahead.run(compile_step)


@eqx.filter_jit
def _step(solver, z, problem: LeastSquares, state):
    z, state, _ = solver.step(_fn, z, problem, {}, state, frozenset())
    done, result = solver.terminate(_fn, z, problem, {}, state, frozenset())
    return z, state, done, result, state.y_eval


class TrustRegion(optx.ClassicalTrustRegion):
    """`optx.ClassicalTrustRegion` that also accepts a step whose predicted and actual
    cost changes are both below `ROUNDING` of the cost.

    At the optimum of a cost summed over 10⁶–10⁷ residuals, the actual change of a
    Gauss–Newton step is rounding noise of either sign; the classical rule then rejects
    step after step (shrinking the region each time) until one happens to decrease the
    cost, and Optimistix tests termination only on accepted steps. Accepting such a step
    lets the step and cost-change criterion decide at once.
    """

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, new_state = super().step(
            first_step, y, y_eval, f_info, f_eval_info, state
        )
        y_diff = jax.tree.map(jnp.subtract, y_eval, y)
        level = ROUNDING * jnp.abs(f_info.as_min())
        flat = (-self.predict_reduction(y_diff, f_info) <= level) & (
            f_eval_info.as_min() - f_info.as_min() <= level
        )
        keep = flat & ~accept
        step_size = jnp.where(keep, state.step_size, step_size)
        new_state = eqx.tree_at(lambda s: s.step_size, new_state, step_size)
        return step_size, accept | flat, result, new_state


def default_solver() -> optx.AbstractLeastSquaresSolver:
    """Levenberg–Marquardt: Optimistix's damped Newton descent in `TrustRegion`."""
    return eqx.tree_at(
        lambda s: s.search, optx.LevenbergMarquardt(rtol=RTOL, atol=ATOL), TrustRegion()
    )


def solve(
    normal: Callable,
    data: Any,
    theta0,
    free,
    *,
    n_residuals: int | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 50,
    start: tuple | None = None,
    size: int | None = None,
    damping: float | None = None,
) -> Solution:
    """Minimise ``cost(θ)`` over the `free` entries of θ, starting at `theta0`.

    - `normal(theta, data) -> (H, b, cost)`: pure and jit-compatible (module docstring);
      define it at module level so that repeated solves share one compilation (or
      mark it `composed`, when it runs kernels of its own).
    - `free`: `(p,)` bool mask; the other entries stay at `theta0`.
    - `n_residuals`: number of scalar residuals behind `normal`; fewer than free
      parameters is a `UserError`.
    - `solver`: any Optimistix least-squares solver (default `default_solver()`).
    - `start`: ``normal(theta0, data)`` if the caller has it already (saves a pass).
    - `size`: the size of the solver's variable, at least the number of free entries
      (default `padded_size` of it): the solver works on the free block of the normal
      equations only, padded to this size; one compilation of its step per size.
    - `damping`: the initial damping of a trust-region solver's step, relative to 1 =
      1/`DIAGONAL` of the scaled diagonal (Optimistix's start). Smaller starts closer to
      Gauss–Newton: for a problem nearly linear from its start (an angle error map of
      hundreds of knots, from zero), whose determined directions span many decades of
      curvature, the damping would otherwise hold the weakly determined ones back for
      several steps while the trust region widens.

    Optimistix's own ``init``/``step``/``terminate`` run the algorithm; between steps the
    normal equations are evaluated at the point the solver asks for (compiled once, apart
    from the solver's small linear algebra), so a step costs one pass over the data.

    A non-finite start (θ₀ or the cost there) is a `UserError`; a solve that stops
    before Optimistix's criterion held returns ``converged=False`` with the reason.
    """
    theta0 = jax.device_put(np.asarray(theta0, np.float64))
    free = np.asarray(free, bool)
    if n_residuals is not None and n_residuals < int(free.sum()):
        raise UserError(
            f"{n_residuals} residuals for {int(free.sum())} free parameters: the fit needs at "
            "least as many observations as parameters"
        )
    if not np.all(np.isfinite(np.asarray(theta0))):
        raise UserError("the start values are not finite")
    h, b, cost = normal_at(normal, theta0, data) if start is None else start
    if not (np.isfinite(float(cost)) and np.all(np.isfinite(np.asarray(h)))):
        raise UserError("the cost at the start is not finite: non-finite observations or weights?")
    solver = solver or default_solver()
    idx = np.flatnonzero(free)
    n = padded_size(idx.size) if size is None else int(size)
    if n < idx.size:
        raise ValueError(f"size {n} is below the {idx.size} free parameters")
    on = np.zeros(n)
    on[: idx.size] = 1.0
    where = _Free(theta0, jax.device_put(np.pad(idx, (0, n - idx.size)).astype(np.int32)))
    hf, bf = _restrict(h, b, where.index)
    scale = np.ones(n)
    scale[: idx.size] = column_scale(np.asarray(hf))[: idx.size] / DIAGONAL**0.5
    z = jnp.zeros(n)
    problem = LeastSquares(
        z=z,
        h=hf,
        b=bf,
        cost=cost,
        scale=jax.device_put(scale),
        free=jax.device_put(on),
    )
    state = _initial_state(solver, n)
    if damping is not None:
        state = eqx.tree_at(lambda st: st.search_state.step_size, state, jnp.asarray(1.0 / damping))
    done, result, steps = False, optx.RESULTS.successful, 0
    # the last two points evaluated (the accepted iterate is one of them, or the start)
    seen = [(np.asarray(z), (h, b, cost))]
    while steps < max_steps:
        z, state, done, result, z_eval = _step(solver, z, problem, state)
        steps += 1
        if bool(done):
            break
        theta = where.theta(problem, z_eval)
        h, b, cost = normal_at(normal, theta, data)
        seen = [*seen[-1:], (np.asarray(z_eval), (h, b, cost))]
        hf, bf = _restrict(h, b, where.index)
        problem = eqx.tree_at(lambda q: (q.z, q.h, q.b, q.cost), problem, (z_eval, hf, bf, cost))
    z_final = np.asarray(z)
    at = next((nq for zs, nq in seen if np.array_equal(zs, z_final)), None)
    theta = where.theta(problem, z)
    cost = float(jnp.sum(state.f_info.residual**2))  # |R|² = cost
    ok = bool(done) and bool(result == optx.RESULTS.successful) and bool(np.isfinite(cost))
    if ok:
        reason = "step and cost change below tolerance"
    elif not np.isfinite(cost):
        reason = "non-finite cost"
    elif not bool(done):
        reason = f"no convergence in {max_steps} steps"
    else:
        reason = str(result).split("<", 1)[-1].rstrip(">") or "solver failed"
    return Solution(np.array(theta), cost, ok, reason, steps, at)
