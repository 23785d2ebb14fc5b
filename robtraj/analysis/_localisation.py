"""Where the gap lives (DESIGN section 7): per variable, the fraction of the held-out gap
that a smooth function of that variable alone removes, with its uncertainty.

A smooth function of a variable v moves an observation's residual by
``Σ_c Σ_k β_ck B_k(v) C_c``: basis functions B_k of v (`basis`: piecewise-linear hat
functions on v's quantiles, or an indicator per value of a categorical v) times
channels C_c `(3,)`, the directions the residual can take (for the discrepancy search
the three camera axes and the observation's displacement per radian of each joint
angle, so that it describes an LED displacement in a fixed direction as well as a
joint angle error; `_gap_localisation`). Adding it to a model moves the model's own
parameters too (the rigid transforms absorb part of any effect), so the residual is
fitted with it *and* with global nuisance directions N `(3, g)` (the first-order change
of the fit's parameters): the linearised refit of the model with the function added.

Both are fitted by weighted least squares on one fold of the held-out check's
alternate time blocks and predict the other, both ways; on the held-out observations

    fraction = 1 − gap²_after / gap²_before

where gap² = Σ(|r − r̂|² − 3σ̂²)/n (as `_residual_stats.gap`, the noise taken out),
r̂ the prediction of the refit with the function (after) or without it (before, the
nuisance alone). Its σ is the delete-one-block jackknife over the time blocks. A
function that does not generalise to the blocks it was not fitted to has a fraction
≤ 0.

The fit works on *units*: the observations of one frame (for a variable of the frame,
such as a joint angle) or one observation (a variable of the LED, such as its emission
angle), reduced once to their normal-equation moments (`moments`), so that trying a
variable costs a pass over units, not over observations.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy import sparse

#: hat functions of a continuous variable (on its quantiles)
KNOTS = 8
#: an integer-valued variable with at most this many values is categorical (an
#: indicator per value: LED, program segment)
MAX_CATEGORIES = 32
#: relative eigenvalue below which a direction of the (column-scaled) normal matrix is
#: left out of the fit (not determined by the training fold)
RCOND = 1e-10


@dataclasses.dataclass(frozen=True)
class Moments:
    """The residual r of `U` units as the fit sees it, with channels C `(3, c)` and
    nuisance directions N `(3, g)` per observation.

    Per unit: weighted ``gw = Σ w CᵀC`` `(U, c, c)`, ``bw = Σ w Cᵀr`` `(U, c)`,
    ``nw = Σ w NᵀC`` `(U, g, c)`, the same unweighted (`gu`, `bu`, `nu`),
    ``excess = Σ(|r|² − 3σ̂²)`` [m²], the number of observations `count` and the time
    `block` (int). Per block `(B, …)`: ``nnw = Σ w NᵀN``, ``nrw = Σ w Nᵀr`` and the
    same unweighted (`nnu`, `nru`)."""

    gw: np.ndarray
    bw: np.ndarray
    nw: np.ndarray
    gu: np.ndarray
    bu: np.ndarray
    nu: np.ndarray
    excess: np.ndarray
    count: np.ndarray
    block: np.ndarray
    nnw: np.ndarray
    nrw: np.ndarray
    nnu: np.ndarray
    nru: np.ndarray


def moments(
    residual: np.ndarray,
    weight: np.ndarray,
    var3: np.ndarray,
    channels: np.ndarray,
    nuisance: np.ndarray,
    block: np.ndarray,
    blocks: int,
) -> Moments:
    """The `Moments` of units of `L` observations each.

    **Arguments:**

    - `residual`: `(U, L, 3)` [m], NaN where there is none.
    - `weight`: `(U, L)` the fit's weights 1/σ² per axis [1/m²]; 0 leaves one out.
    - `var3`: `(U, L)` 3σ̂² [m²] of each observation (NaN: left out).
    - `channels`: `(U, L, 3, c)` the directions of each observation's residual.
    - `nuisance`: `(U, L, 3, g)` the global directions refitted with every function
      (g may be 0).
    - `block`: `(U,)` int in [0, `blocks`), the time block of each unit.
    """
    use = np.isfinite(residual[..., 0]) & np.isfinite(var3) & (weight > 0)
    u, n_obs, _, c = channels.shape
    g = nuisance.shape[-1]
    r = np.where(use[..., None], residual, 0.0).reshape(u, n_obs * 3)
    w = np.repeat(np.where(use, weight, 0.0), 3, axis=1)
    ch = np.where(use[..., None, None], channels, 0.0).reshape(u, n_obs * 3, c)
    nz = np.where(use[..., None, None], nuisance, 0.0).reshape(u, n_obs * 3, g)
    chw, nzt = ch * w[..., None], np.swapaxes(nz, 1, 2)
    r2 = np.sum(r.reshape(u, n_obs, 3) ** 2, -1)
    block = np.asarray(block)
    # the nuisance's own products are only needed per block: one product of its rows each
    nnw, nrw = np.zeros((blocks, g, g)), np.zeros((blocks, g))
    nnu, nru = np.zeros((blocks, g, g)), np.zeros((blocks, g))
    for b in np.unique(block):
        rows = nz[block == b].reshape(-1, g)
        wb, rb = w[block == b].ravel(), r[block == b].ravel()
        nnw[b], nnu[b] = rows.T @ (rows * wb[:, None]), rows.T @ rows
        nrw[b], nru[b] = rows.T @ (wb * rb), rows.T @ rb
    return Moments(
        gw=np.swapaxes(ch, 1, 2) @ chw,
        bw=np.einsum("uic,ui->uc", chw, r),
        nw=nzt @ chw,
        gu=np.swapaxes(ch, 1, 2) @ ch,
        bu=np.einsum("uic,ui->uc", ch, r),
        nu=nzt @ ch,
        excess=np.where(use, r2 - np.where(use, var3, 0.0), 0.0).sum(1),
        count=use.sum(1),
        block=block,
        nnw=nnw,
        nrw=nrw,
        nnu=nnu,
        nru=nru,
    )


def merged(parts: Sequence[Moments]) -> Moments:
    """The `Moments` of the units of all `parts` (computed a chunk of units at a time)."""
    per_unit = ("gw", "bw", "nw", "gu", "bu", "nu", "excess", "count", "block")
    return Moments(
        **{k: np.concatenate([getattr(p, k) for p in parts]) for k in per_unit},
        **{k: sum(getattr(p, k) for p in parts) for k in ("nnw", "nrw", "nnu", "nru")},
    )


@dataclasses.dataclass(frozen=True)
class Basis:
    """A basis of `size` functions of a variable, at most two non-zero per unit: the
    value of function `first` is `a_first`, that of `second` is `a_second` (0 for a
    unit without a value)."""

    first: np.ndarray
    second: np.ndarray
    a_first: np.ndarray
    a_second: np.ndarray
    size: int


def basis(values: np.ndarray, knots: int = KNOTS) -> Basis | None:
    """The basis of a variable with `values` `(U,)` per unit (NaN: none): an indicator
    per value when they are integers of at most `MAX_CATEGORIES` values, else the
    `knots` piecewise-linear hat functions on its quantiles (a partition of unity: a
    constant is in it); None when it takes fewer than two values."""
    ok = np.isfinite(values)
    v = np.where(ok, values, 0.0)
    seen = np.unique(v[ok])
    if seen.size < 2:
        return None
    if seen.size <= MAX_CATEGORIES and np.all(seen == np.round(seen)):
        k = np.searchsorted(seen, v).clip(0, seen.size - 1)
        return Basis(k, k, ok.astype(float), np.zeros_like(v), seen.size)
    t = np.unique(np.quantile(v[ok], np.linspace(0.0, 1.0, knots)))
    k = np.clip(np.searchsorted(t, v, side="right") - 1, 0, t.size - 2)
    upper = np.where(ok, np.clip((v - t[k]) / (t[k + 1] - t[k]), 0.0, 1.0), 0.0)
    return Basis(k, k + 1, np.where(ok, 1.0 - upper, 0.0), upper, t.size)


def heldout_fraction(
    mom: Moments, b: Basis, groups: Sequence[Sequence[int]] | None = None, floor2: float = 0.0
) -> tuple[float, float]:
    """The fraction of the held-out gap² that a smooth function in basis `b` removes,
    fitted (with the nuisance) on odd blocks to predict even ones and on even ones to
    predict odd ones, and its delete-one-block jackknife σ.

    `groups`: the function moves the residual along the channels of one group (indices
    into the channels of `mom`), the one whose fit on the training fold has the best
    AIC (χ² decrease against the nuisance alone less 2 per coefficient; "a displacement
    in a fixed direction" or "joint j's angle error", not both at once), or along none
    when no group's AIC is positive; None: all channels form one group.
    `floor2` [m²]: a gap² below it counts as it (the gap's floor², below which the gap
    is noise and a fraction of it means nothing); NaN when the gap² is ≤ 0 and there is
    no floor."""
    n_blocks = mom.nnw.shape[0]
    fold_of_block = np.arange(n_blocks) % 2
    fold = mom.block % 2
    gain = np.zeros(n_blocks)  # Σ|r|² − Σ|r − r̂|² per block, with the function
    gain0 = np.zeros(n_blocks)  # the same, nuisance alone
    pair, one = _spread(b)
    for f in (0, 1):
        train, train_blocks = fold != f, fold_of_block != f
        delta, beta, delta0 = _fit(mom, b.size, pair, one, train, train_blocks, groups)
        held = np.flatnonzero(fold == f)
        gamma = (
            b.a_first[held, None] * beta[:, b.first[held]].T
            + b.a_second[held, None] * beta[:, b.second[held]].T
        )
        # 2 r̂ᵀr − |r̂|² of r̂ = Cγ + Nδ, in the unit's moments (Nδ's own terms per block)
        gu_gamma = np.einsum("ucd,ud->uc", mom.gu[held], gamma)
        nu_delta = np.tensordot(delta, mom.nu[held], axes=(0, 1))
        per_unit = np.einsum("uc,uc->u", gamma, 2.0 * mom.bu[held] - gu_gamma - 2.0 * nu_delta)
        gain += np.bincount(mom.block[held], per_unit, minlength=n_blocks)
        hb = fold_of_block == f
        for d, out in ((delta, gain), (delta0, gain0)):
            out[hb] += 2.0 * mom.nru[hb] @ d - np.einsum("g,bgh,h->b", d, mom.nnu[hb], d)
    excess = np.bincount(mom.block, mom.excess, minlength=n_blocks)
    count = np.bincount(mom.block, mom.count, minlength=n_blocks)
    present = count > 0
    parts = [x[present] for x in (gain - gain0, excess - gain0, count)]
    whole = _ratio(*(p.sum() for p in parts), floor2)
    # delete-one-block jackknife
    jack = np.array(
        [_ratio(*(p.sum() - p[k] for p in parts), floor2) for k in range(parts[0].size)]
    )
    n = jack.size
    sigma = float(np.sqrt((n - 1) / n * np.sum((jack - jack.mean()) ** 2))) if n > 1 else np.inf
    return whole, sigma


def _ratio(gained: float, gap2: float, count: float, floor2: float) -> float:
    """gained / max(gap2, count · floor2); NaN for a denominator ≤ 0."""
    den = max(float(gap2), float(count) * floor2)
    return float(gained) / den if den > 0 else float("nan")


def _spread(b: Basis) -> tuple[sparse.csr_matrix, sparse.csr_matrix]:
    """`(size², U)` the products ``B_k B_l`` of each unit's basis functions (row
    ``k·size + l``) and `(size, U)` the functions ``B_k``, sparse: each unit has at most
    two."""
    k, u = b.size, b.first.size
    units = np.arange(u)
    lo, hi, a, d = b.first, b.second, b.a_first, b.a_second
    pair = sparse.csr_matrix(
        (
            np.concatenate([a * a, d * d, a * d, d * a]),
            (
                np.concatenate([lo * k + lo, hi * k + hi, lo * k + hi, hi * k + lo]),
                np.tile(units, 4),
            ),
        ),
        shape=(k * k, u),
    )
    one = sparse.csr_matrix(
        (np.concatenate([a, d]), (np.concatenate([lo, hi]), np.tile(units, 2))), shape=(k, u)
    )
    return pair, one


def _fit(
    mom: Moments,
    k: int,
    pair: sparse.csr_matrix,
    one: sparse.csr_matrix,
    train: np.ndarray,
    train_blocks: np.ndarray,
    groups: Sequence[Sequence[int]] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weighted least-squares fit to the `train` units: nuisance δ `(g,)` and
    function β `(c, k)` together (β zero outside the group chosen), and δ₀ of the
    nuisance alone. The normal matrix's function block ``Σ_u gw_u ⊗ B_u B_uᵀ`` and its
    cross block ``Σ_u nw_u ⊗ B_uᵀ`` are sparse products over the units (`_spread`)."""
    u, c = mom.bw.shape
    g = mom.nnw.shape[-1]
    z = train.astype(float)[:, None]
    hff = (pair @ (mom.gw.reshape(u, c * c) * z)).reshape(k, k, c, c).transpose(2, 0, 3, 1)
    hnf = (one @ (mom.nw.reshape(u, g * c) * z)).reshape(k, g, c).transpose(1, 2, 0)
    hnn, rn = mom.nnw[train_blocks].sum(0), mom.nrw[train_blocks].sum(0)
    h = np.block([[hnn, hnf.reshape(g, c * k)], [hnf.reshape(g, c * k).T, hff.reshape(c * k, -1)]])
    rhs = np.concatenate([rn, (one @ (mom.bw * z)).T.reshape(c * k)])
    delta0 = _solve(hnn, rn)
    # the nuisance alone is a candidate too (AIC 0): a function no group's fit supports
    best, out = 0.0, np.concatenate([delta0, np.zeros(c * k)])
    for grp in [range(c)] if groups is None else groups:
        idx = np.concatenate(
            [np.arange(g), g + (np.asarray(grp)[:, None] * k + np.arange(k)).ravel()]
        )
        x = _solve(h[np.ix_(idx, idx)], rhs[idx])
        # AIC: the χ² decrease against the nuisance alone, less 2 per coefficient
        aic = 2.0 * x @ rhs[idx] - x @ h[np.ix_(idx, idx)] @ x - delta0 @ rn - 2.0 * (idx.size - g)
        if aic > best:
            best, out = aic, np.zeros(g + c * k)
            out[idx] = x
    return out[:g], out[g:].reshape(c, k), delta0


def _solve(h: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The minimum-norm solution of ``h x = rhs`` in the column-scaled space, directions
    with relative eigenvalue below `RCOND` left out (undetermined by the fold)."""
    if h.size == 0:
        return np.zeros_like(rhs)
    d = np.sqrt(np.clip(np.diag(h), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    lam, vec = np.linalg.eigh(h / np.outer(d, d))
    keep = lam > RCOND * max(lam.max(), 0.0)
    if not keep.any():
        return np.zeros_like(rhs)
    x = vec[:, keep] @ ((vec[:, keep].T @ (rhs / d)) / lam[keep])
    return x / d
