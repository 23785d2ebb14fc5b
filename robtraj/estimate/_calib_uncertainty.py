"""The uncertainty of a bundle fit at its estimate (`Uncertainty`): the normal equations
there (per cluster for the cluster-robust covariance), χ² and the variance factor, the
covariances of the reported parameters that the quoted σ takes the largest of
(`quoted_sigma`: Gauss–Newton, the delete-one-cluster jackknife and the covariance under
a model-error field over the clusters' joint angles, `cluster_field`), the log
likelihood, and what the recording determines: the identifiability report with the
parameters fixed and the rigid-transform parameters determined only weakly."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np

from . import _calib_problem as cp
from ._calib_clusters import padded_clusters
from ._calib_parameters import reported_names
from ._calib_problem import bundle_normal, bundle_normal_clustered
from ._calib_residuals import Residuals, residuals_at
from ._calib_setup import Setup
from ._calib_solves import Solved
from ._cluster_field import cluster_field
from ._compile_ahead import in_background
from ._quoted_sigma import quoted_sigma, sigma_of
from ._solve import normal_at
from ._uncertainty import covariance, effective_clusters, robust_covariance

#: σ above which a determined rigid-transform parameter is reported as weak: translation
#: [m] ("t…") and rotation [rad] ("r…", 0.1 mm at 1 m): a third of the tracker's noise
#: and what ISO 9283 accuracies of tenths of a millimetre can no longer ignore
WEAK_SIGMA = {"t": 20e-6, "r": 100e-6}


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    """The fit's uncertainty at its estimate: the normal matrix `h` in θ, χ² of the
    observations (without the terms' prior), the residual and parameter counts, the
    variance factor ``s2 = χ²/(n − rank)``; the reported parameters' `names`, their
    Gauss–Newton `covariance` ``s2·H⁺`` and cluster-robust one (the Gauss–Newton one
    where it is not computed), the clusters each robust σ rests on (NaN there) and the
    cluster count (probe poses included); the covariance under the model-error field
    (`covariance_field`, None where not estimated) and the field (`model_error`,
    `ModelErrorField.as_dict`, empty there); the log likelihood and the identifiability
    report (`robtraj.estimate.identifiability`, with ``fixed_parameters`` and
    ``weak``)."""

    h: np.ndarray
    chi2: float
    n_residuals: int
    rank: int
    s2: float
    names: list[str]
    covariance: np.ndarray
    covariance_robust: np.ndarray
    clusters_effective: np.ndarray
    n_clusters: int
    covariance_field: np.ndarray | None
    model_error: dict[str, Any]
    log_likelihood: float
    identifiability: dict[str, Any]


def uncertainty(
    st: Setup, solved: Solved, clustered: bool, say: Callable[[str], None]
) -> tuple[Uncertainty, Residuals]:
    """The uncertainty at `solved`'s estimate (`clustered`: with the cluster-robust
    covariance and the model-error field), and the residuals there (`_calib_residuals`),
    summarised while the normal equations are accumulated on a background thread."""
    say("covariance and residual statistics")
    st.ahead.wait()
    bundle, free, q = solved.bundle, solved.free, st.q
    p_theta = jnp.zeros(len(st.names_theta))
    cluster, n_clusters = st.clusters
    if clustered:
        padded = padded_clusters(n_clusters)
        final = in_background(bundle_normal_clustered, p_theta, bundle, cluster, padded)
    else:
        final = in_background(normal_at, bundle_normal, p_theta, bundle)
    res = residuals_at(st, solved)
    if clustered:
        h, _, chi2, cluster_h, scores = (np.asarray(x) for x in final.result())
        keep = np.r_[np.arange(n_clusters), np.arange(padded, cluster_h.shape[0])]
        cluster_h, scores = cluster_h[keep], scores[keep]
    else:
        h, _, chi2 = (np.asarray(x) for x in final.result())
    # χ² of the observations: the normal equations' cost holds the terms' prior too
    chi2 = float(chi2) - float(bundle.prior.cost(cp.prior_values(jnp.zeros(q), bundle)))
    cov_unit, rank = covariance(h, free)
    s2 = chi2 / max(1, st.n_residuals - rank)
    t = _reported(q, st.data.n_leds, np.asarray(bundle.basis))
    cov = t @ (s2 * cov_unit) @ t.T
    if clustered:
        cov_robust = t @ robust_covariance(h, free, cluster_h, scores) @ t.T
        g_eff = effective_clusters(h, free, cluster_h, t)
        field = _field(st, solved, res, h, free, cluster_h[:n_clusters], scores[:n_clusters])
        del cluster_h, scores
    else:
        cov_robust, g_eff, field = cov, np.full(t.shape[0], np.nan), None
    cov_field = None if field is None else t @ field[1] @ t.T
    names = reported_names(st.names_theta, q, st.data.led_ids)
    unc = Uncertainty(
        h=h,
        chi2=chi2,
        n_residuals=st.n_residuals,
        rank=rank,
        s2=s2,
        names=names,
        covariance=cov,
        covariance_robust=cov_robust,
        clusters_effective=g_eff,
        n_clusters=int(n_clusters + (bundle.probe.probed.shape[0] if bundle.probe else 0)),
        covariance_field=cov_field,
        model_error={} if field is None else field[0].as_dict(),
        log_likelihood=_log_likelihood(chi2, res.log_weight_sum, res.n_used),
        identifiability=_determined(st, solved, names, cov, cov_robust, cov_field),
    )
    return unc, res


def _field(st: Setup, solved: Solved, res: Residuals, h, free, cluster_h, scores):
    """`cluster_field` of the recording's clusters (probe poses left out): each at the
    logged joint angles [rad] of its weighted mean time (robot clock t + τ), weighted by
    its observations' final weights. None where it cannot be estimated."""
    data, n = st.data, cluster_h.shape[0]
    label = np.asarray(st.clusters[0]).reshape(-1)[: data.n_frames]
    frame_w = res.frame_weight
    weight = np.bincount(label, frame_w, n)
    keep = weight > 0
    tau = float(np.asarray(solved.bundle.problem.effects.time_offset))
    t = np.bincount(label, frame_w * data.time, n)[keep] / weight[keep] + tau
    joints = np.stack([np.interp(t, data.log_time, q) for q in data.joints.T], -1)
    tx = np.array([st.names_theta.index(f"camera_from_base.t{c}") for c in "xyz"])
    try:
        return cluster_field(
            h, free, cluster_h[keep], scores[keep], joints, weight[keep], res.median_weight, tx
        )
    except np.linalg.LinAlgError:  # the clusters' sums do not determine every parameter
        return None


def _reported(q: int, n_leds: int, basis: np.ndarray) -> np.ndarray:
    """The map `(q + 3·leds, q + c)` from θ to the reported parameters (the constellation
    basis on its coefficients)."""
    t = np.zeros((q + 3 * n_leds, q + basis.shape[1]))
    t[:q, :q] = np.eye(q)
    t[q:, q:] = basis
    return t


def _log_likelihood(chi2: float, log_weight_sum: float, n_used: int) -> float:
    """The Gaussian log likelihood of the LED observations at the estimate, their
    variances ``σ̂²/w`` with the variance factor at its maximum ``χ²/n`` (``Σ log w``
    and the count over the `n_used` observations of non-zero weight)."""
    n_led = 3 * int(n_used)
    logw = float(log_weight_sum) * 3.0
    return -0.5 * n_led * (math.log(2 * math.pi * chi2 / n_led) + 1.0) + 0.5 * logw


def _determined(st: Setup, solved: Solved, names, cov, cov_robust, cov_field) -> dict[str, Any]:
    """The identifiability report at the start, with the parameters of the model left
    fixed (``fixed_parameters``) and the rigid-transform parameters whose quoted σ
    exceeds `WEAK_SIGMA` (``weak``)."""
    ident = solved.identifiability
    ident = {
        **ident,
        "fixed_parameters": [
            names[i] for i in range(st.q) if st.in_model[i] and not solved.free[i]
        ],
    }
    sig = quoted_sigma(sigma_of(cov), sigma_of(cov_robust), sigma_of(cov_field)).sigma
    ident["weak"] = _weak(names[:12], sig[:12], set(ident["undetermined"]))
    return ident


def _weak(names, sigma, undetermined) -> list[dict[str, Any]]:
    """Rigid-transform parameters determined, but with σ above `WEAK_SIGMA`."""
    out = []
    for name, s in zip(names, sigma):
        tol = WEAK_SIGMA[name.rsplit(".", 1)[1][0]]
        if name not in undetermined and s > tol:
            out.append({"parameter": name, "sigma": float(s), "tolerance": tol})
    return out
