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
discrepancy of Kennedy and O'Hagan, J. R. Stat. Soc. B 63, 2001), shared in form by the
output components c and independent between them: ``u_c = a·f_c + ε``, ``a`` the field's
relative amplitude per point, ``ε`` white of variance ``s²``, and ``f_c`` of covariance
``s² Σ_k κ_k exp(−|x − x'|²/(2ℓ_k²))``: one variance per correlation length of
`FIELD_LENGTHS`, so that short-range structure (what the residual shows most) does not
decide how much error is correlated across the whole workspace (what moves the
parameters). The covariance is exact (no feature approximation): nothing in the answer
depends on an approximation's size.

The variances κ are estimated by restricted maximum likelihood (profiled over s²) on up
to `FIELD_SUBSAMPLE` points (seeded): with ``V = I + Σ κ_k D K_k D``, ``D = diag(a)``,
``M = Σ_c A_cᵀV⁻¹A_c`` and ``Q = Σ_c ŷ_cᵀV⁻¹ŷ_c`` the generalised residual cost,

    −2 log L_R(κ) = (N − p) log Q + C log|V| + log|M|,

minimised over log κ with its analytic gradient. A field is kept only if it lowers
−2 log L_R by the 1 % point of its null distribution (`field_threshold`: a mixture of χ²
for variances on their boundary); white noise finds a small smooth-looking part by chance.
Parameters under a prior (random effects the fit already models, such as the knots of
a map) are held at their estimate in the likelihood and their covariance is not computed.
The estimate is left as the fit made it; its covariance under the field is the sandwich
``s_w²·H⁻¹(H + Σ_c A_cᵀ D K D A_c)H⁻¹`` on all points, ``s_w² = s²·w``, w the share of
the residual variance the field leaves white: where no field is found it is the
Gauss–Newton covariance exactly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.sparse
import scipy.stats
from jaxtyping import Float
from scipy.spatial.distance import cdist

from .._blas import serial_blas

#: correlation lengths of the field's components, in the units of the configuration x
FIELD_LENGTHS = (0.1, 0.3, 1.0, 3.0)
#: the most points the variances are estimated on (a seeded subsample)
FIELD_SUBSAMPLE = 1500
#: log κ searched over this interval; at its lower end a component is absent
LOG_KAPPA_RANGE = (-12.0, 9.0)
#: false-field rate of the acceptance test
FIELD_ALPHA = 0.01
#: rows of the kernel formed at once in the sandwich
_BLOCK = 2048


@dataclasses.dataclass(frozen=True)
class ModelErrorField:
    """The model-error field fitted to a residual and what it does to the parameters.

    `lengths`: the correlation lengths (units of x); `ratios` `(K,)`: each component's
    variance κ_k over the white variance (whitened units; zero where absent);
    `white`: the share of the residual variance left white, ``Q(κ̂)/Q(0)``;
    `deviance`: the decrease of −2 log L_R against no field; `covariance` `(q, q)`: the
    covariance of the parameters without a prior per unit residual variance (multiply by
    the fit's ``s²``; the rows and columns of ``H⁻¹`` where no field is found).
    """

    lengths: tuple[float, ...]
    ratios: np.ndarray
    white: float
    deviance: float
    covariance: np.ndarray

    @property
    def found(self) -> bool:
        return bool(np.any(self.ratios > 0))

    def as_dict(self) -> dict[str, object]:
        return {
            "lengths": list(self.lengths),
            "ratios": [float(k) for k in self.ratios],
            "white_share": self.white,
            "deviance": self.deviance,
        }


def field_threshold(k: int, alpha: float = FIELD_ALPHA) -> float:
    """The (1 − α) point of ``Σ_j C(k, j) 2⁻ᵏ χ²_j``, the null distribution of the
    likelihood-ratio statistic of k variances on their boundary (Self and Liang 1987,
    treating them as orthogonal)."""
    w = scipy.stats.binom.pmf(np.arange(k + 1), k, 0.5)

    def tail(t):
        return sum(w[j] * scipy.stats.chi2.sf(t, j) for j in range(1, k + 1)) - alpha

    return float(scipy.optimize.brentq(tail, 1e-6, 200.0))


class _Reml:
    """−2 log L_R and its gradient in log κ on the points of `rows`, `residual`."""

    def __init__(self, rows, residual, x, amplitude, lengths):
        d2 = cdist(x, x, "sqeuclidean")
        self.k = [np.outer(amplitude, amplitude) * np.exp(-d2 / (2.0 * ell**2)) for ell in lengths]
        self.a = np.concatenate(rows, 1)  # (n, C p): the components side by side
        self.y = np.stack(residual, 1)  # (n, C)
        self.c, self.p = len(rows), rows[0].shape[1]
        self.n_obs = self.c * x.shape[0]

    def __call__(self, log_kappa: np.ndarray, grad: bool = True):
        kappa = np.exp(log_kappa)
        n, c, p = self.y.shape[0], self.c, self.p
        v = np.eye(n) + sum(kk * kk_ for kk, kk_ in zip(kappa, self.k))
        chol = scipy.linalg.cho_factor(v, lower=True)
        logdet_v = 2.0 * np.sum(np.log(np.diag(chol[0])))
        w = scipy.linalg.cho_solve(chol, np.c_[self.a, self.y])
        wa, wy = w[:, : c * p], w[:, c * p :]
        m = sum(self.a[:, i * p : (i + 1) * p].T @ wa[:, i * p : (i + 1) * p] for i in range(c))
        b = sum(self.a[:, i * p : (i + 1) * p].T @ wy[:, i] for i in range(c))
        mc = scipy.linalg.cho_factor(m)
        beta = scipy.linalg.cho_solve(mc, b)
        u = wy - np.stack([wa[:, i * p : (i + 1) * p] @ beta for i in range(c)], 1)  # V⁻¹ŷ
        q = float(np.sum(self.y * u))
        dof = self.n_obs - p
        val = dof * np.log(q) + c * logdet_v + 2.0 * np.sum(np.log(np.diag(mc[0])))
        if not grad:
            return val, q
        vinv = scipy.linalg.cho_solve(chol, np.eye(n))
        minv = scipy.linalg.cho_solve(mc, np.eye(p))
        g = np.empty(len(kappa))
        for j, kj in enumerate(self.k):
            kwa = kj @ wa
            t_m = sum(
                np.sum((wa[:, i * p : (i + 1) * p] @ minv) * kwa[:, i * p : (i + 1) * p])
                for i in range(c)
            )
            dq = -float(np.sum(u * (kj @ u)))
            g[j] = kappa[j] * (dof * dq / q + c * np.sum(vinv * kj) - t_m)
        return (val, q), g


@serial_blas
def field_covariance(
    h: Float[np.ndarray, "p p"],
    rows: Sequence[np.ndarray | scipy.sparse.spmatrix],
    residual: Float[np.ndarray, "c n"],
    x: Float[np.ndarray, "n d"],
    amplitude: Float[np.ndarray, " n"],
    flat: np.ndarray | None = None,
    *,
    lengths: Sequence[float] = FIELD_LENGTHS,
    subsample: int = FIELD_SUBSAMPLE,
    seed: int = 0,
) -> ModelErrorField:
    """The model-error field of a fit and the covariance of its parameters under it.

    - `h`: the normal matrix of the free parameters (whitened; with any prior), positive
      definite.
    - `rows`: per output component c, the whitened Jacobian rows `(n, p)` (dense or
      `scipy.sparse`) of the n points; `residual` `(c, n)` the whitened residual at the
      estimate.
    - `x` `(n, d)`: where each point was taken (the field's argument); `amplitude`
      `(n,)`: the field's relative standard deviation per point in whitened units (a
      point weighted less than the others sees the same physical field smaller).
    - `flat` `(p,)`: the parameters without a prior (default all); only their
      covariance is returned.
    """
    h = np.asarray(h, float)
    p = h.shape[0]
    flat = np.ones(p, bool) if flat is None else np.asarray(flat, bool)
    x = np.asarray(x, float)
    amplitude = np.asarray(amplitude, float)
    n = x.shape[0]
    hinv_flat = scipy.linalg.solve(h, np.eye(p)[:, flat], assume_a="pos").T  # (q, p)
    sub = np.arange(n)
    if n > subsample:
        sub = np.sort(np.random.default_rng(seed).choice(n, subsample, replace=False))

    def dense(r, idx=slice(None)):
        r = r[idx]
        return np.asarray(r.toarray() if hasattr(r, "toarray") else r, float)

    reml = _Reml(
        [dense(r, sub)[:, flat] for r in rows],
        [np.asarray(e, float)[sub] for e in residual],
        x[sub],
        amplitude[sub],
        lengths,
    )
    lo, hi = LOG_KAPPA_RANGE
    k = len(lengths)
    null, q0 = reml(np.full(k, -60.0), grad=False)
    best = None
    for start in (-3.0, 1.0):
        res = scipy.optimize.minimize(
            lambda z: (lambda vg: (vg[0][0], vg[1]))(reml(z)),
            np.full(k, start),
            jac=True,
            method="L-BFGS-B",
            bounds=[(lo, hi)] * k,
        )
        if best is None or res.fun < best.fun:
            best = res
    deviance = float(null - best.fun)
    if deviance < field_threshold(k):
        ratios, white = np.zeros(k), 1.0
    else:
        ratios = np.where(best.x > lo + 1e-3, np.exp(best.x), 0.0)
        white = reml(np.log(np.maximum(ratios, 1e-300)), grad=False)[1] / q0
    cov = hinv_flat @ h @ hinv_flat.T
    if np.any(ratios > 0):
        z = np.concatenate([amplitude[:, None] * np.asarray(r @ hinv_flat.T) for r in rows], 1)
        g = np.zeros((z.shape[1], z.shape[1]))
        for s in range(0, n, _BLOCK):
            d2 = cdist(x[s : s + _BLOCK], x, "sqeuclidean")
            kz = sum(
                kk * np.exp(-d2 / (2.0 * ell**2)) for kk, ell in zip(ratios, lengths) if kk > 0
            )
            g += z[s : s + _BLOCK].T @ (kz @ z)
        q = hinv_flat.shape[0]
        # the components are independent: only their diagonal blocks count
        cov = cov + sum(g[i * q : (i + 1) * q, i * q : (i + 1) * q] for i in range(len(rows)))
    return ModelErrorField(
        lengths=tuple(float(ell) for ell in lengths),
        ratios=ratios,
        white=float(white),
        deviance=deviance,
        covariance=white * cov,
    )
