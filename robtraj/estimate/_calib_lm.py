"""Levenberg–Marquardt over chunk-accumulated normal equations, identifiability analysis.

The global problem has ~70 parameters but up to 10⁶ frames × 18 LEDs × 3 residuals,
so the Jacobian is never materialised: each iteration accumulates ``JᵀJ`` and ``Jᵀr``
chunk by chunk (`_calib_problem.normal_equations`), solves the damped, column-scaled
system ``(D⁻¹JᵀJD⁻¹ + μI) z = D⁻¹Jᵀr`` with lineax (Cholesky), and accepts the step
``δ = D⁻¹z`` when the chunk-accumulated cost drops (μ ÷ 3), else rejects it (μ × 8).
Accepted steps are absorbed into the problem (tangent-space re-centring), so every
linearisation is at the current estimate and the final ``JᵀJ`` is the Gauss–Newton
normal matrix at the optimum (used for the covariance).

Identifiability: the column-scaled normal matrix (unit diagonal) is eigen-decomposed;
eigenvalues below ``rcond · λ_max`` are null-space directions. Their parameters are
named; an effect parameter in a null direction is fixed at its initial value (dropped
from the free set), a remaining null direction is left unmoved by the (pseudo-inverse)
step and excluded from the parameter count.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import jaxlie
import lineax as lx
import numpy as np
import scipy.linalg

from . import _calib_problem as cp

RCOND = 1e-10


@dataclasses.dataclass
class Normal:
    H: np.ndarray
    b: np.ndarray
    cost: float


def assemble(parts, basis: np.ndarray, extra=None) -> Normal:
    """Normal equations in θ = [global, constellation coefficients] from chunk sums."""
    hgg, hgp, hpp, bg, bp, c = (np.asarray(x) for x in parts)
    if extra is not None:  # probe terms on the global parameters
        hgg, bg, c = hgg + extra[0], bg + extra[1], c + extra[2]
    q, m = hgg.shape[0], hpp.shape[0]
    hgp_b = hgp.reshape(q, 3 * m) @ basis
    hpp_b = basis.T @ scipy.linalg.block_diag(*hpp) @ basis
    H = np.block([[hgg, hgp_b], [hgp_b.T, hpp_b]])
    b = np.concatenate([bg, basis.T @ bp.reshape(-1)])
    return Normal(0.5 * (H + H.T), b, float(c))


def recentre(problem: cp.BundleProblem, delta: np.ndarray, q: int) -> cp.BundleProblem:
    """Absorb a θ step into the problem's current values."""
    d = jnp.asarray(delta)
    cfb = jaxlie.SE3(problem.camera_from_base) @ jaxlie.SE3.exp(d[:6])
    fft = jaxlie.SE3(problem.flange_from_tool) @ jaxlie.SE3.exp(d[6:12])
    eff = cp.apply_effects(problem.effects, problem.free, d[12:q])
    p = problem.constellation + (problem.gauge_basis @ d[q:]).reshape(-1, 3)
    return eqx.tree_at(
        lambda pr: (pr.camera_from_base, pr.flange_from_tool, pr.effects, pr.constellation),
        problem,
        (cfb.wxyz_xyz, fft.wxyz_xyz, eff, p),
    )


def scale_of(H: np.ndarray) -> np.ndarray:
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    floor = 1e-12 * (d.max() if d.size and d.max() > 0 else 1.0)
    return np.where(d > floor, d, 1.0)


def identifiability(
    H: np.ndarray, names: list[str], free: np.ndarray, droppable: np.ndarray, rcond: float = RCOND
) -> tuple[np.ndarray, dict]:
    """Drop droppable (effect) parameters that lie in null directions; report all of them.

    Returns the new free mask and a report ``{"condition", "dropped", "null_directions"}``.
    """
    free = free.copy()
    dropped, unresolved = [], []
    d = scale_of(H)
    while True:
        idx = np.flatnonzero(free)
        hs = H[np.ix_(idx, idx)] / np.outer(d[idx], d[idx])
        lam, vec = np.linalg.eigh(hs)
        null = lam < rcond * lam[-1]
        if not null.any():
            break
        v = vec[:, np.flatnonzero(null)[0]]
        big = np.abs(v) > 0.1 * np.abs(v).max()
        involved = [names[idx[i]] for i in np.flatnonzero(big)]
        cand = [i for i in np.flatnonzero(big) if droppable[idx[i]]]
        if not cand:
            unresolved = [
                [
                    names[idx[i]]
                    for i in np.flatnonzero(np.abs(vec[:, k]) > 0.1 * np.abs(vec[:, k]).max())
                ]
                for k in np.flatnonzero(null)
            ]
            break
        worst = max(cand, key=lambda i: abs(v[i]))
        free[idx[worst]] = False
        dropped.append({"parameter": names[idx[worst]], "confounded_with": involved})
    idx = np.flatnonzero(free)
    lam = np.linalg.eigvalsh(H[np.ix_(idx, idx)] / np.outer(d[idx], d[idx]))
    good = lam[lam > rcond * lam[-1]]
    report = {
        "condition_number": float(lam[-1] / good[0]) if good.size else float("inf"),
        "rcond": rcond,
        "dropped": dropped,
        "null_directions": unresolved,
    }
    return free, report


def pinv_scaled(H: np.ndarray, free: np.ndarray, rcond: float = RCOND) -> tuple[np.ndarray, int]:
    """Pseudo-inverse of H on the free block (zero elsewhere) and its rank."""
    idx = np.flatnonzero(free)
    d = scale_of(H)[idx]
    hs = H[np.ix_(idx, idx)] / np.outer(d, d)
    lam, vec = np.linalg.eigh(hs)
    keep = lam > rcond * lam[-1]
    inv_s = (vec[:, keep] / lam[keep]) @ vec[:, keep].T
    out = np.zeros_like(H)
    out[np.ix_(idx, idx)] = inv_s / np.outer(d, d)
    return out, int(keep.sum())


def _solve(hs: np.ndarray, bs: np.ndarray, mu: float) -> np.ndarray:
    op = lx.MatrixLinearOperator(
        jnp.asarray(hs + mu * np.eye(hs.shape[0])), lx.positive_semidefinite_tag
    )
    sol = lx.linear_solve(op, jnp.asarray(bs), lx.Cholesky(), throw=False)
    z = np.asarray(sol.value)
    if not np.all(np.isfinite(z)):
        z = np.linalg.lstsq(hs + mu * np.eye(hs.shape[0]), bs, rcond=None)[0]
    return z


def levenberg_marquardt(
    normal_fn, cost_fn, problem, free: np.ndarray, q: int, *, max_iter: int = 50, tol: float = 1e-10
):
    """Minimise over the free θ entries; returns ``(problem, normal, iterations, converged)``.

    `normal_fn(problem) -> Normal`, `cost_fn(problem) -> float`.
    """
    normal = normal_fn(problem)
    idx = np.flatnonzero(free)
    mu = 1e-4
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        d = scale_of(normal.H)[idx]
        hs = normal.H[np.ix_(idx, idx)] / np.outer(d, d)
        bs = normal.b[idx] / d
        z = _solve(hs, bs, mu)
        # cost = Σ w r², linearised: c − 2 bᵀδ + δᵀHδ
        predicted = float(2.0 * z @ bs - z @ hs @ z)
        if predicted <= tol * max(normal.cost, 1e-300):
            converged = True
            break
        delta = np.zeros(normal.H.shape[0])
        delta[idx] = z / d
        cand = recentre(problem, delta, q)
        c_new = cost_fn(cand)
        if np.isfinite(c_new) and c_new < normal.cost:
            gain = (normal.cost - c_new) / max(predicted, 1e-300)
            problem = cand
            small = normal.cost - c_new <= tol * normal.cost
            normal = normal_fn(problem)
            mu = max(mu / (3.0 if gain > 0.25 else 1.0), 1e-12)
            if small:
                converged = True
                break
        else:
            mu *= 8.0
            if mu > 1e12:
                break
    return problem, normal, it, converged
