"""Model error as a random field: the parameters' covariance when the residual a model
leaves is a smooth function of where the data were taken.

A least-squares fit with whitened residuals ``e = A θ + u`` treats ``u`` as white noise;
its Gauss–Newton covariance ``s²H⁻¹`` then shrinks with every added point. When the model
misses a systematic effect, ``u`` is a function of the configuration ``x`` at which each
point was taken, and the part of it that looks like the model's own columns biases θ by
an amount that depends on the design: two recordings of one machine over different sets
of configurations disagree by far more than ``s²H⁻¹``, and no resampling of one
recording's points sees it (deleting a region of a design barely moves the design-mean
of a field that is correlated across the whole workspace).

Here the model error is a zero-mean Gaussian field over ``x`` (the linearised model
discrepancy of Kennedy and O'Hagan, J. R. Stat. Soc. B 63, 2001): per output component c,
``u_c(x) = σ_c(x)·f_c(x) + white``, with ``f_c`` independent fields of squared-exponential
covariance of length ℓ and variance ``κ·s²`` (κ relative to the white variance ``s²``).
The field is represented by `FIELD_FEATURES` random Fourier features (Rahimi and Recht
2007; one seeded draw, so the result is reproducible) and (ℓ, κ) are estimated from the
residual by restricted maximum likelihood: with ``U`` the features' whitened columns and
``M = I − A H⁻¹ Aᵀ`` the projection the fit leaves, ``λ_i``, ``v_i`` the eigenpairs of
``UᵀMU`` and ``z = Uᵀe``,

    −2 log L_R(κ) = (n − p) log Q(κ) + Σ log(1 + κλ_i),   Q(κ) = eᵀe − Σ (v_iᵀz)² κ/(1 + κλ_i)

(profiled over s²), κ by a bounded search per ℓ of `FIELD_LENGTHS`. A field is kept only
if it lowers −2 log L_R by `FIELD_DEVIANCE` against none (κ = 0): white noise finds a
small smooth-looking part by chance, and a long-ℓ field, looking like the model's own
columns, would widen the σ for nothing. The estimate is left as the fit made it; its covariance under the field is the
sandwich ``s_w²·H⁻¹(H + κ GGᵀ)H⁻¹``, ``G = AᵀU``, with the white variance
``s_w² = s²·Q(κ̂)/eᵀe``: where the residual shows no field (κ̂ = 0) it is the Gauss–Newton
covariance exactly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import scipy.linalg
import scipy.optimize
from jaxtyping import Float

from ._uncertainty import column_scale

#: correlation lengths tried for the field, in the units of the configuration x
FIELD_LENGTHS = (0.1, 0.2, 0.5, 1.0, 2.0)
#: random Fourier features per output component
FIELD_FEATURES = 150
#: relative field variance κ searched over [KAPPA_RANGE], and κ = 0
KAPPA_RANGE = (1e-6, 1e3)
#: the least decrease of −2 log L_R for which a field is accepted: the 1 % point of the
#: boundary test of one variance (½χ²₀ + ½χ²₁), 5 % for the best of five lengths
FIELD_DEVIANCE = 5.41


@dataclasses.dataclass(frozen=True)
class ModelErrorField:
    """The model-error field fitted to a residual and what it does to the parameters.

    `length`: correlation length ℓ (units of x; NaN where no field was found); `ratio`: κ,
    the field's variance over the white residual variance (whitened units); `white`: the
    share of the residual cost left as white noise, ``Q(κ̂)/eᵀe``; `covariance` `(p, p)`:
    the free parameters' covariance per unit residual variance (multiply by the fit's
    ``s²``; equal to ``H⁻¹`` where κ = 0); `at_edge`: ℓ is the largest or smallest tried.
    """

    length: float
    ratio: float
    white: float
    covariance: np.ndarray
    at_edge: bool

    def as_dict(self) -> dict[str, float | bool]:
        return {
            "length": self.length,
            "ratio": self.ratio,
            "white_share": self.white,
            "length_at_edge": self.at_edge,
        }


def random_features(
    x: Float[np.ndarray, "n d"], length: float, m: int = FIELD_FEATURES, seed: int = 0
) -> Float[np.ndarray, "n m"]:
    """`m` random Fourier features of the unit-variance squared-exponential covariance of
    length `length` at the points `x` (``φ(x)ᵀφ(x') ≈ exp(−|x − x'|²/(2ℓ²))``)."""
    rng = np.random.default_rng(seed)
    omega = rng.normal(size=(m, x.shape[1])) / length
    phase = rng.uniform(0.0, 2 * np.pi, m)
    return np.sqrt(2.0 / m) * np.cos(np.asarray(x, float) @ omega.T + phase)


def _reml(ee: float, lam: np.ndarray, zh2: np.ndarray, dof: float):
    """−2 log L_R and Q as functions of log κ (see the module docstring)."""

    def q_of(kappa):
        return ee - np.sum(zh2 * kappa / (1.0 + kappa * lam))

    def objective(log_kappa):
        k = np.exp(log_kappa)
        return dof * np.log(q_of(k)) + np.sum(np.log1p(k * lam))

    return objective, q_of


def field_covariance(
    h: Float[np.ndarray, "p p"],
    rows: Sequence,
    residual: Float[np.ndarray, "c n"],
    x: Float[np.ndarray, "n d"],
    amplitude: Float[np.ndarray, "c n"],
    *,
    cost: float,
    dof: float,
    lengths: Sequence[float] = FIELD_LENGTHS,
    m: int = FIELD_FEATURES,
    seed: int = 0,
) -> ModelErrorField:
    """The model-error field of a fit and the parameters' covariance under it.

    - `h`: the normal matrix of the free parameters (whitened; with any prior), positive
      definite.
    - `rows`: per output component c, the whitened Jacobian rows `(n, p)` (dense or
      `scipy.sparse`) of the n points; `residual` `(c, n)` the whitened residual.
    - `x` `(n, d)`: where each point was taken (the field's argument); `amplitude`
      `(c, n)`: the field's standard deviation per component and point in whitened
      units, relative (a point weighted less than the others sees the same physical
      field smaller in whitened units).
    - `cost`: the fit's whitened cost at the estimate (with any prior's); `dof`: its
      residual degrees of freedom.
    """
    h = np.asarray(h, float)
    d = column_scale(h)
    hs = scipy.linalg.cho_factor(h / np.outer(d, d))

    def h_solve(b):
        return scipy.linalg.cho_solve(hs, b / d[:, None]) / d[:, None]

    best = None
    for length in lengths:
        phi = random_features(x, length, m, seed)
        u = [phi * np.asarray(a, float)[:, None] for a in amplitude]
        g = np.concatenate([np.asarray(r.T @ uc) for r, uc in zip(rows, u)], 1)
        gram = scipy.linalg.block_diag(*[uc.T @ uc for uc in u])
        z = np.concatenate([uc.T @ np.asarray(e, float) for uc, e in zip(u, residual)])
        hig = h_solve(g)
        lam, vec = np.linalg.eigh(gram - g.T @ hig)
        lam = np.clip(lam, 0.0, None)
        objective, q_of = _reml(cost, lam, (vec.T @ z) ** 2, dof)
        grid = np.linspace(*np.log(KAPPA_RANGE), 40)
        vals = np.array([objective(v) for v in grid])
        i = int(np.argmin(vals))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        res = scipy.optimize.minimize_scalar(objective, bounds=(lo, hi), method="bounded")
        kappa, val = float(np.exp(res.x)), float(res.fun)
        if val > dof * np.log(cost) - FIELD_DEVIANCE:  # no field: the white noise's chance
            kappa, val = 0.0, dof * np.log(cost)
        if best is None or val < best[0]:
            best = (val, length, kappa, q_of(kappa) / cost, hig)
    _, length, kappa, white, hig = best
    cov = white * (h_solve(np.eye(h.shape[0])) + kappa * hig @ hig.T)
    return ModelErrorField(
        length=float(length) if kappa > 0 else float("nan"),
        ratio=kappa,
        white=float(white),
        covariance=cov,
        at_edge=kappa > 0 and length in (min(lengths), max(lengths)),
    )
