"""Blocked cross-validation of pose-level models inside one series, by one Gauss–Newton
step per left-out region.

The poses of a series are split into `regions` of joint space (k-means). A model's
cross-validation error is the error of each region's poses predicted by the model fitted
to the other regions. The fit without region g is taken as one Gauss–Newton step from
the model's linearisation at θ (the whole series' fit, or the current model of a
search, with a candidate's entries added at zero)::

    Δ_g = (H − H_g + Λ)⁻¹ (b − b_g − Λc)      (on the free entries)

with ``H, b`` the weighted normal equations of the series, ``H_g, b_g`` those of region
g, Λ the prior of the terms that carry one and c their values; the held-out residual is
``r + J·Δ_g`` on region g's poses. The pose model is nearly linear in its corrections
(tens of µrad and µm on a metre-sized arm), so the step is the refit to well below the
errors compared (checked against refits in `tests/analysis/test_real_ur10.py`); it
costs one pass over the poses for every candidate of a round and every left-out region,
where refits would cost a fit each.
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from ..estimate import column_scale, map_jvp, spd_inverse


@dataclasses.dataclass(frozen=True)
class Linearisation:
    """A series' normal equations at θ, in total and per region, and what the held-out
    predictions need: `h`, `b` `(P, P)`, `(P,)` (weighted data, no prior), `h_g`, `b_g`
    per region, `cost` ``rᵀWr``, the unweighted residual `r` `(N, 6)` (position [m],
    rotation vector [rad]), the dense Jacobian `j` `(N, 6, n_dense)` of the entries
    before the maps' knots, the maps' active knots, every pose's region `label` and where
    the joint offsets lie in θ (`offset`, the maps' columns follow from theirs)."""

    theta: np.ndarray
    label: np.ndarray
    h: np.ndarray
    b: np.ndarray
    cost: float
    h_g: np.ndarray
    b_g: np.ndarray
    r: np.ndarray
    j: np.ndarray
    map_index: np.ndarray
    map_weight: np.ndarray
    offset: tuple[int, int]

    @property
    def n_dense(self) -> int:
        return int(self.j.shape[-1])

    @property
    def n_regions(self) -> int:
        return int(self.h_g.shape[0])

    @functools.cached_property
    def on_device(self) -> tuple:
        """`j`, `map_index`, `map_weight` and `label` as JAX arrays (copied once)."""
        return tuple(jnp.asarray(a) for a in (self.j, self.map_index, self.map_weight, self.label))


def posterior(lin: Linearisation, prior: np.ndarray | None):
    """``(H + Λ, b − Λθ)``: the normal equations with the prior `prior` `(P, P)` (dense
    over θ, or None)."""
    if prior is None:
        return lin.h, lin.b
    return lin.h + prior, lin.b - prior @ lin.theta


def step(h: np.ndarray, b: np.ndarray, free: np.ndarray) -> np.ndarray:
    """``H⁻¹b`` on the `free` entries (zero elsewhere): Cholesky of the column-scaled
    block, or its least-squares solution where that is not positive definite."""
    idx = np.flatnonzero(free)
    out = np.zeros(h.shape[-1])
    if not idx.size:
        return out
    out[idx] = solve_scaled(h[np.ix_(idx, idx)], b[idx])
    return out


def solve_scaled(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``a⁻¹ rhs`` for a symmetric `a`: Cholesky of the column-scaled matrix, or its
    least-squares solution where that is not positive definite."""
    d = column_scale(a)
    scaled = a / np.outer(d, d)
    r = rhs / (d[:, None] if rhs.ndim == 2 else d)
    try:
        x = scipy.linalg.cho_solve(scipy.linalg.cho_factor(scaled, check_finite=False), r)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(scaled, r, rcond=1e-10)[0]
    return x / (d[:, None] if rhs.ndim == 2 else d)


class RegionSystems:
    """The systems ``(H + Λ − H_g) δ = b − Λθ − b_g`` of every left-out region g (and of
    the whole series, last), with the free knots of the maps eliminated once: per
    system, the solve of the map block gives the Schur complement onto the other
    entries, `(n_dense, n_dense)`, from which the step of any model that shares those
    knots (and the prior) is a small solve. A round of the search scores every
    candidate from one set of these.

    A region's poses touch only the knots near their angles (a few hundred of a
    thousand), so its map block is that of the whole series less a term on those knots:
    every region's solve is the whole series' inverse corrected on its own knots
    (`_Downdates`), one factorisation in all instead of one per region."""

    def __init__(self, lin: Linearisation, prior: np.ndarray | None, map_free: np.ndarray):
        n = self.n_dense = lin.n_dense
        self.map_free = np.asarray(map_free[n:], bool)
        m = self.m = np.flatnonzero(self.map_free) + n
        self.p = lin.theta.size
        d = np.arange(n)
        b = lin.b if prior is None else lin.b - prior @ lin.theta
        lam = (lambda r, c: 0.0) if prior is None else (lambda r, c: _block(prior, r, c))
        h_dd = lin.h[:n, :n] + lam(d, d)
        # the whole series last: its region terms are zero
        hg_dd = np.concatenate([lin.h_g[:, :n, :n], np.zeros((1, n, n))])
        bg = np.concatenate([lin.b_g, np.zeros((1, self.p))])
        self.schur = list(h_dd - hg_dd)
        self.rhs = list(b[:n] - bg[:, :n])
        self.y, self.ym = [], []
        if not m.size:
            return
        h_mm = _block(lin.h, m, m) + lam(m, m)
        h_md = _block(lin.h, m, d) + lam(m, d)
        rhs = np.concatenate([h_md, b[m][:, None]], 1)
        whole = _Downdates.of(h_mm, rhs)
        for g in range(lin.n_regions + 1):
            # the region's free knots, its block of H_mm there and its rows of [H_md, b_m]
            if g < lin.n_regions:
                on = _touched(lin.h_g[g], m)
                k = m[on]
                u = _block(lin.h_g[g], k, k)
                lost = np.concatenate([_block(lin.h_g[g], k, d), lin.b_g[g, k][:, None]], 1)
            else:  # the whole series
                on, u, lost = np.zeros(0, int), np.zeros((0, 0)), np.zeros((0, n + 1))
            both = None if whole is None else whole.solve(on, u, lost)
            if both is None:
                a_mm, r = h_mm.copy(), rhs.copy()
                a_mm[np.ix_(on, on)] -= u
                r[on] -= lost
                both = solve_scaled(a_mm, r)
            a_md = h_md.copy()
            a_md[on] -= lost[:, :-1]
            ymd, ym = both[:, :-1], both[:, -1]
            self.schur[g] = self.schur[g] - a_md.T @ ymd
            self.rhs[g] = self.rhs[g] - a_md.T @ ym
            self.y.append(ymd)
            self.ym.append(ym)

    def steps(self, free: np.ndarray) -> np.ndarray:
        """`(G + 1, P)`: the step on the `free` entries of each system (its map knots must
        be those the systems eliminated)."""
        n = self.n_dense
        if not np.array_equal(free[n:], self.map_free):
            raise ValueError("the free map knots differ from those eliminated")
        dense = np.flatnonzero(free[:n])
        out = np.zeros((len(self.schur), self.p))
        for g, (s, r) in enumerate(zip(self.schur, self.rhs)):
            x = solve_scaled(s[np.ix_(dense, dense)], r[dense]) if dense.size else np.zeros(0)
            out[g, dense] = x
            if self.m.size:
                out[g, self.m] = self.ym[g] - self.y[g][:, dense] @ x
        return out


class _Downdates:
    """Solves ``(A − E U Eᵀ) x = rhs − E l`` for one symmetric positive definite A and
    one right-hand side `rhs`, where E picks a few of A's rows (a region's knots): A is
    inverted once (the Cholesky factor of its column-scaled form) and each solve is the
    Woodbury identity ``(A − EUEᵀ)⁻¹ = A⁻¹ + A⁻¹E U (I − C U)⁻¹ EᵀA⁻¹``,
    ``C = EᵀA⁻¹E``, a system of the picked rows' size (no inverse of U, which a
    region's data need not make regular)."""

    def __init__(self, inv: np.ndarray, scale: np.ndarray, rhs: np.ndarray):
        # the inverse of the scaled matrix, the scale and A⁻¹·rhs in scaled units
        self.inv, self.scale = inv, scale
        self.base = inv @ (rhs / scale[:, None])

    @classmethod
    def of(cls, a: np.ndarray, rhs: np.ndarray) -> _Downdates | None:
        """None where the scaled `a` is not numerically positive definite."""
        d = column_scale(a)
        inv = spd_inverse(a / np.outer(d, d))
        return None if inv is None else cls(inv, d, rhs)

    def solve(self, on: np.ndarray, u: np.ndarray, lost: np.ndarray) -> np.ndarray | None:
        """x for the rows `on`, their block `u` and right-hand side rows `lost`; None
        where ``I − CU`` is singular."""
        d, inv = self.scale, self.inv
        if not on.size:
            return self.base / d[:, None]
        ds = d[on]
        us = u / np.outer(ds, ds)
        cols = inv[:, on]
        y = self.base - cols @ (lost / ds[:, None])
        try:
            z = scipy.linalg.solve(np.eye(on.size) - cols[on] @ us, y[on], check_finite=False)
        except np.linalg.LinAlgError:
            return None
        return (y + cols @ (us @ z)) / d[:, None]


def _touched(h_g: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Positions in `m` (the free knots) of the knots a region's normal matrix `h_g`
    touches: a knot's row is zero exactly where its diagonal is (``Σ φ²|u|²``, Cauchy–
    Schwarz), and so is its entry of b."""
    return np.flatnonzero(np.diagonal(h_g)[m] != 0.0)


def _block(a: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``a[rows][:, cols]`` (a copy)."""
    return a[np.ix_(rows, cols)]


def region_steps(lin: Linearisation, free: np.ndarray, prior: np.ndarray | None) -> np.ndarray:
    """`(G, P)`: the Gauss–Newton step from `lin.theta` of the fit without each region
    (module docstring), on the `free` entries."""
    return RegionSystems(lin, prior, free).steps(free)[:-1]


def held_out(lin: Linearisation, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and rotation angle [rad] of every pose predicted with its region
    left out (`steps` from `region_steps`): the norms of ``r + J·Δ_{region}``."""
    label, n = lin.label, lin.n_dense
    res = lin.r + np.einsum("nkp,np->nk", lin.j, steps[label, :n])
    if steps.shape[1] > n:
        j, index, weight, group = lin.on_device
        res = res + np.asarray(
            map_jvp(j, lin.offset, index, weight, jnp.asarray(steps[:, n:]), group)
        )
    return np.linalg.norm(res[:, :3], axis=1), np.linalg.norm(res[:, 3:], axis=1)


def cv_error(lin: Linearisation, steps: np.ndarray) -> dict[str, float]:
    """The blocked cross-validation error of the model whose left-out steps are `steps`
    (`region_steps`, `RegionSystems.steps`): RMS and mean of the held-out position error
    [m] and rotation angle [rad]."""
    pos, ang = held_out(lin, steps[: lin.n_regions])
    return {
        "pos_rms_m": float(np.sqrt(np.mean(pos**2))),
        "ang_rms_rad": float(np.sqrt(np.mean(ang**2))),
        "pos_mean_m": float(np.mean(pos)),
        "ang_mean_rad": float(np.mean(ang)),
    }


def gain(before: dict[str, float], after: dict[str, float]) -> float:
    """Relative decrease of the cross-validation error: the mean of those of the position
    RMS and the angle RMS (negative: worse)."""
    g = [(before[k] - after[k]) / before[k] for k in ("pos_rms_m", "ang_rms_rad")]
    return float(0.5 * (g[0] + g[1]))
