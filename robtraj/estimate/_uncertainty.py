"""Identifiability and covariance from the normal matrix ``H = JᵀWJ`` at the optimum.

Both work on the column-scaled matrix ``D⁻¹HD⁻¹`` (D = sqrt(diag H), unit diagonal), so
that the threshold does not depend on the parameters' units. One threshold, `RCOND`:
an eigenvalue below ``RCOND · λ_max`` of the scaled matrix is a null direction — the
data do not tell that combination of parameters apart (a singular value of the
unit-norm-column Jacobian below 1e-5 of the largest).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.linalg

#: relative eigenvalue of the column-scaled normal matrix below which a direction is null
RCOND = 1e-10


def column_scale(h: np.ndarray) -> np.ndarray:
    """D = sqrt(diag H), with 1 for columns without information (`h` may be a stack
    `(..., p, p)`)."""
    d = np.sqrt(np.clip(np.diagonal(h, axis1=-2, axis2=-1), 0.0, None))
    top = d.max(-1, keepdims=True) if d.shape[-1] else np.ones(d.shape[:-1] + (1,))
    floor = 1e-12 * np.where(top > 0, top, 1.0)
    return np.where(d > floor, d, 1.0)


def _scaled(h: np.ndarray, idx: np.ndarray, d: np.ndarray) -> np.ndarray:
    return h[np.ix_(idx, idx)] / np.outer(d[idx], d[idx])


def identifiability(
    h: np.ndarray,
    names: Sequence[str],
    free: np.ndarray,
    droppable: np.ndarray,
    *,
    prefer: Sequence[str] = (),
) -> tuple[np.ndarray, dict[str, Any]]:
    """Fix droppable parameters that lie in null directions of `h`; name them.

    Repeatedly, for the smallest null direction of the free block: among its droppable
    parameters with a component ≥ 0.2 of the largest, fix the first one listed in
    `prefer`, else the one with the largest component. Each fixed parameter is reported
    with what it is confounded with: the free parameters whose (unit-norm) columns
    combine to its own with a coefficient above 0.05, largest first. Null directions
    without a droppable parameter are reported in ``null_directions`` (the solve leaves
    them unmoved, the covariance excludes them).

    Returns the new free mask and ``{"condition_number", "rcond", "dropped",
    "null_directions", "undetermined"}``; ``undetermined`` lists, in `names` order, the
    free parameters with a component above 0.1 of the largest in a null direction: the
    data do not determine them (their variance is not finite, whatever the
    pseudo-inverse gives).
    """
    free = np.asarray(free, bool).copy()
    droppable = np.asarray(droppable, bool)
    d = column_scale(h)
    no_info = np.diag(h) <= 0
    dropped: list[str] = []
    unresolved: list[list[str]] = []
    while True:
        idx = np.flatnonzero(free)
        lam, vec = np.linalg.eigh(_scaled(h, idx, d))
        null = np.flatnonzero(lam < RCOND * lam[-1])
        if not null.size:
            break
        v = np.abs(vec[:, null[0]])
        cand = [k for k in np.flatnonzero(v >= 0.2 * v.max()) if droppable[idx[k]]]
        if not cand:
            unresolved = [
                [
                    names[idx[k]]
                    for k in np.flatnonzero(np.abs(vec[:, j]) > 0.1 * np.abs(vec[:, j]).max())
                ]
                for j in null
            ]
            break
        known = [(list(prefer).index(names[idx[k]]), k) for k in cand if names[idx[k]] in prefer]
        k = min(known)[1] if known else max(cand, key=lambda c: v[c])
        free[idx[k]] = False
        dropped.append(names[idx[k]])
    idx = np.flatnonzero(free)
    hs = _scaled(h, idx, d)
    lam = np.linalg.eigvalsh(hs)
    good = lam[lam > RCOND * lam[-1]]
    inv = np.linalg.pinv(hs, rcond=RCOND, hermitian=True)
    report = []
    for name in dropped:
        i = list(names).index(name)
        if no_info[i]:
            report.append({"parameter": name, "confounded_with": ["(no effect on the data)"]})
            continue
        coef = inv @ (h[idx, i] / d[idx] / d[i])
        order = np.argsort(-np.abs(coef))
        # in a null direction yet explained by no other column: its own column is
        # numerical noise (a gravity torque of rounding size, say)
        others = [names[idx[m]] for m in order if abs(coef[m]) > 0.05]
        report.append({"parameter": name, "confounded_with": others or ["(no effect on the data)"]})
    return free, {
        "condition_number": float(lam[-1] / good[0]) if good.size else float("inf"),
        "rcond": RCOND,
        "dropped": report,
        "null_directions": unresolved,
        "undetermined": [n for n in names if any(n in group for group in unresolved)],
    }


def covariance(h: np.ndarray, free: np.ndarray, s2: float = 1.0) -> tuple[np.ndarray, int]:
    """``s² · H⁺`` on the free block (zero rows and columns elsewhere) and its rank.

    The pseudo-inverse is taken of the column-scaled block, leaving out its null
    directions (`RCOND`); ``s² = χ²/(n − rank)`` makes it the covariance of a fit whose
    weights are known only up to a common factor.
    """
    inv, rank = _pinv(h, free)
    return s2 * inv, rank


def robust_covariance(
    h: np.ndarray, free: np.ndarray, cluster_h: np.ndarray, scores: np.ndarray
) -> np.ndarray:
    """Cluster-robust covariance on the free block (zero rows and columns elsewhere): the
    delete-one-cluster jackknife, each cluster's deletion taken as one Gauss–Newton step
    from the optimum, ``δ_g = (H − H_g)⁺ s_g``, and ``(G−1)/G Σ_g (δ_g − δ̄)(δ_g − δ̄)ᵀ``.

    `cluster_h` `(G, p, p)` and `scores` `(G, p)` are each cluster's normal matrix
    ``J_gᵀW J_g`` and score ``J_gᵀW r_g`` at the optimum (they sum to `h` and to zero).
    It needs no assumption that the residuals are noise: when the model misses an
    effect, the residuals of one cluster (a robot pose, a region of the workspace) share
    it and the estimate moves with the cluster left out, where ``s² H⁺`` assumes the
    misfit independent from one observation to the next and shrinks as more are taken.
    Clusters must be independent of each other. With the model right it agrees with
    `covariance` up to its sampling error (relative ≈ ``1/√(2G)`` on a σ) and, unlike the
    plain sandwich ``H⁺ Σ s_g s_gᵀ H⁺``, without the downward bias of clusters that
    carry much of the information on a parameter (the jackknife's ``(H − H_g)⁺``).
    """
    s = np.asarray(scores, float)
    g = s.shape[0]
    if g < 2:
        return np.full(np.shape(h), np.nan)
    inv, _ = _pinv(np.asarray(h, float) - np.asarray(cluster_h, float), free)
    return jackknife_covariance(np.einsum("gij,gj->gi", inv, s))


def jackknife_covariance(delta: np.ndarray) -> np.ndarray:
    """``(G−1)/G Σ_g (δ_g − δ̄)(δ_g − δ̄)ᵀ`` of the delete-one-cluster changes `delta`
    `(G, p)` (`robust_covariance`; a problem that solves the deletions its own way, e.g.
    with a block it eliminates first, passes them here)."""
    g = delta.shape[0]
    if g < 2:
        return np.full((delta.shape[1], delta.shape[1]), np.nan)
    dev = delta - delta.mean(0)
    return (g - 1) / g * dev.T @ dev


def effective_clusters(
    h: np.ndarray, free: np.ndarray, cluster_h: np.ndarray, t: np.ndarray | None = None
) -> np.ndarray:
    """Per parameter, how many clusters the robust σ effectively rests on:
    ``1 / Σ_g w_g²`` with ``w_g`` cluster g's share of the parameter's variance where the
    model is right, ``diag(T H⁺ H_g H⁺ Tᵀ)`` normalised (`t` maps the free block to the
    reported parameters; identity when None). The relative sampling error of the robust
    σ is about ``1/√(2·G_eff)``: a constellation entry of an LED seen in a few dwells
    rests on a few clusters however many the recording has. NaN where undetermined."""
    hp, _ = _pinv(np.asarray(h, float), free)
    a = hp if t is None else np.asarray(t, float) @ hp
    part = np.sum((a @ np.asarray(cluster_h, float)) * a, -1)  # aᵐ H_g aᵐ per g, m
    total = part.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = part / total
        return np.where(total > 0, 1.0 / np.sum(share**2, 0), np.nan)


def _pinv(h: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray | int]:
    """Pseudo-inverse of the column-scaled free block of `h` (or of each matrix of a stack
    `(..., p, p)`), null directions below `RCOND` left out; zero elsewhere. Returns it and
    its rank (an array for a stack). A single matrix well above `RCOND` (LAPACK's
    estimate of its condition, `WELL_CONDITIONED`) is inverted from its Cholesky factor:
    no direction would be left out, at a fraction of the eigendecomposition's cost."""
    idx = np.flatnonzero(free)
    d = column_scale(h)[..., idx]
    hs = h[..., idx[:, None], idx] / (d[..., :, None] * d[..., None, :])
    inv = spd_inverse(hs, WELL_CONDITIONED) if hs.ndim == 2 and idx.size else None
    if inv is not None:
        rank = np.asarray(idx.size)
    else:
        lam, vec = np.linalg.eigh(hs)
        keep = lam > RCOND * lam[..., -1:]
        inv_lam = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
        inv = (vec * inv_lam[..., None, :]) @ np.swapaxes(vec, -1, -2)
        rank = keep.sum(-1)
    out = np.zeros(np.shape(h), dtype=float)
    out[..., idx[:, None], idx] = inv / (d[..., :, None] * d[..., None, :])
    return out, int(rank) if rank.ndim == 0 else rank


#: LAPACK's estimate of the reciprocal 1-norm condition number above which `_pinv`
#: inverts by Cholesky: the estimate may exceed the true value, rarely by more than a
#: factor of 10, and ``λ_min/λ_max ≥ 1/κ₁``; so 10⁴·`RCOND` leaves a wide margin
WELL_CONDITIONED = 1e4 * RCOND


def spd_inverse(a: np.ndarray, rcond: float | None = None) -> np.ndarray | None:
    """The inverse of the symmetric matrix `a` from its Cholesky factor, or None where it
    is not numerically positive definite (the factorisation fails) or, with `rcond`,
    where LAPACK's estimate of its reciprocal condition number (1-norm) is below it."""
    c, info = scipy.linalg.lapack.dpotrf(a, lower=1, clean=0)
    if info != 0:
        return None
    if rcond is not None:
        est, info = scipy.linalg.lapack.dpocon(c, float(np.abs(a).sum(0).max()), uplo="L")
        if info != 0 or not est > rcond:
            return None
    inv, info = scipy.linalg.lapack.dpotri(c, lower=1)
    if info != 0:
        return None
    inv = np.tril(inv)
    inv += np.triu(inv.T, 1)
    return inv
