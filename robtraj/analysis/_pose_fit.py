"""Pose-level fit of a UR10 to laser-tracker probe poses: the weights, the identifiable
set, the fit by the package's one engine (`robtraj.estimate.solve`) on the 6-DOF pose
observation kind of `robtraj.estimate` (`pose_normal`: the parameter layout, the
measurement model through `robtraj.model` and its normal equations), its σ and the
regions of joint space it is cross-validated on (see `robtraj.analysis.real_data` for the
model)."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax.numpy as jnp
import jaxlie
import numpy as np
from scipy.cluster.vq import kmeans2

from .._blas import serial_blas
from ..estimate import (
    POSE_HARMONIC_TERMS as HARMONIC_TERMS,
    POSE_MAP_OFFSET,
    POSE_MAP_PARAMS as N_MAP,
    POSE_MAP_TERMS as MAP_TERMS,
    POSE_PARAMS as N_PARAMS,
    POSE_REDUNDANT,
    GaussianPrior,
    ModelErrorField,
    PoseData,
    QuotedSigma,
    covariance,
    field_covariance,
    group_members,
    identifiability,
    jackknife_covariance,
    jacobian_rows,
    map_prior_of,
    map_terms_of,
    no_prior,
    normal_at,
    parse_effect_spec,
    pose_data,
    pose_group_terms,
    pose_n_params as n_params,
    pose_normal,
    pose_parameter_names as parameter_names,
    pose_residual,
    pose_slices,
    predict_probe_poses,
    quoted_sigma,
    sigma_of,
    solve,
    uses_maps,
    zero_map_prior,
)
from ..model import MAP_KNOTS, MAP_LENGTH, MAP_SIGMA_F, map_support
from ._pose_cv import Linearisation, RegionSystems, solve_scaled
from ._pose_series import PoseSeries
from ._quat import rotation_angle

__all__ = [
    "HARMONIC_TERMS",
    "MAP_TERMS",
    "N_MAP",
    "N_PARAMS",
    "map_prior_of",
    "map_terms_of",
    "n_params",
    "parameter_names",
    "parse_effect_spec",
    "uses_maps",
]

_SL = pose_slices()

#: regions of joint space the robust σ leaves out one at a time: the model error of a
#: UR10 varies over the workspace, so a region must span a good part of it
REGIONS = 10
#: which parameter of a null direction to fix first (the UR10's known degeneracies:
#: joint-1 zero ≡ tracker yaw, d1 ≡ tracker z, joint-6 zero ≡ probe roll about the
#: flange axis, d6/a6 ≡ probe offset, d2 + d3 + d4 along parallel axes 2–4 only as a
#: sum, no gravity torque on joints 1 and 6), so that both series fix the same ones
FIX_PREFERENCE = (
    "joint_compliance[0]",
    "joint_compliance[5]",
    "joint_offset[0]",
    "link_length[0].d",
    "joint_offset[5]",
    "link_length[5].d",
    "link_length[5].a",
    "link_length[1].d",
    "link_length[2].d",
)

# ----------------------------------------------------------------------------- parameters


def pose_errors(predicted: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position error [m] and single-angle orientation error [rad] per pose
    (``2·atan2(|q_xyz|, |q_w|)`` of the relative rotation, DESIGN section 6)."""
    pred, meas = np.asarray(predicted), np.asarray(measured)
    pos = np.linalg.norm(pred[:, 4:] - meas[:, 4:], axis=-1)
    return pos, rotation_angle(meas[:, :4], pred[:, :4])


def error_summary(pos: np.ndarray, ang: np.ndarray, noise_m: float = 0.0) -> dict[str, float]:
    """mean / RMS / max position error [mm], orientation error [deg], and the gap [mm]
    (position RMS with the tracker noise taken out, DESIGN section 7)."""
    rms = float(np.sqrt(np.mean(pos**2)))
    return {
        "pos_mean_mm": float(np.mean(pos)) * 1e3,
        "pos_rms_mm": rms * 1e3,
        "pos_max_mm": float(np.max(pos)) * 1e3,
        "ang_mean_deg": float(np.rad2deg(np.mean(ang))),
        "ang_max_deg": float(np.rad2deg(np.max(ang))),
        "gap_mm": math.sqrt(max(0.0, rms**2 - 3 * noise_m**2)) * 1e3,
    }


def tracker_noise(series: PoseSeries) -> float:
    """Per-axis tracker noise σ [m] from its reported standard deviations (0 without)."""
    if series.std is None:
        return 0.0
    return float(np.sqrt(np.mean(series.std[:, :3] ** 2)))


# ----------------------------------------------------------------------------- fit


@dataclasses.dataclass(frozen=True)
class PoseFit:
    """A pose-level calibration of one series.

    `theta`: full parameter vector (`parameter_names`, with the map block when the fit
    carries maps), zero = the start; `z0`, `x0`: camera←base and flange←probe at θ = 0
    (``wxyz_xyz``); `free`: estimated parameters; `fixed_unidentifiable`: effect
    parameters fixed because they are not identifiable (with the direction they are
    confounded with); `sigma`: 1σ of the estimated parameters (`np.nan` elsewhere), the
    quoted σ (`robtraj.estimate.quoted_sigma`; `quoted` says which source set each): the
    largest of `sigma_model` (``s²(JᵀWJ + Λ)⁻¹``, the posterior with the prior Λ of the
    maps, ``s² = χ²/(n − p_eff)``, p_eff the effective parameter count) and, except on
    entries under a prior, two that survive model error (`robust_terms`, computed when
    first asked for): the delete-one-region jackknife over `REGIONS` regions of joint
    space (`robtraj.estimate.robust_covariance`), which does not shrink when the residual
    is model error shared by neighbouring poses, and the covariance under a model-error
    field over the joint angles (`robtraj.estimate.field_covariance`, one variance per
    correlation length), which also covers error correlated across the whole workspace,
    the part that makes two series over different poses disagree. A map's knot is
    determined by the poses near it: leaving out their region leaves it to its prior,
    which the jackknife would measure instead of the estimate.
    `chi2` is the weighted residual sum of squares (without the prior's ``cᵀΛc``);
    `map_prior` the maps' (σ_f, ℓ) [rad] where the fit estimates maps.
    """

    series: str
    estimated: tuple[str, ...]
    theta: np.ndarray
    z0: np.ndarray
    x0: np.ndarray
    free: np.ndarray
    sigma_model: np.ndarray
    chi2: float
    n_residuals: int
    block_sigma: tuple[float, float]
    identifiability: dict[str, Any]
    position_error: np.ndarray
    angle_error: np.ndarray
    iterations: int
    converged: bool
    effective_parameters: float = 0.0
    map_prior: tuple[float, float] | None = None
    #: entries under a Gaussian prior (the estimated maps' knots)
    prior_entries: np.ndarray | None = dataclasses.field(default=None, repr=False)
    #: Gauss–Newton covariance of θ's entries before the maps, `(N_PARAMS, N_PARAMS)`
    #: (zero rows and columns on entries not estimated)
    covariance: np.ndarray | None = dataclasses.field(default=None, repr=False)
    #: the robust σ on demand (None: a cross-series prediction, no effects)
    _robust: Callable[[], dict[str, Any]] | None = dataclasses.field(default=None, repr=False)

    @functools.cached_property
    def robust_terms(self) -> dict[str, Any]:
        """``{"jackknife": σ, "field": σ, "model_error": ModelErrorField.as_dict()}``, the
        σ `(P,)` of the region jackknife and of the model-error field (NaN where not
        estimated); empty without effects."""
        if self._robust is None or not np.any(self.free[12:]):
            return {}
        return self._robust()

    @functools.cached_property
    def quoted(self) -> QuotedSigma:
        """The quoted σ with the source that set each (`robtraj.estimate.quoted_sigma`)."""
        terms = self.robust_terms
        return quoted_sigma(
            self.sigma_model, terms.get("jackknife"), terms.get("field"), prior=self.prior_entries
        )

    @property
    def sigma(self) -> np.ndarray:
        return self.quoted.sigma

    @property
    def n_free(self) -> int:
        return int(self.free.sum())

    @property
    def has_maps(self) -> bool:
        return self.theta.size > N_PARAMS

    @property
    def camera_from_base(self) -> np.ndarray:
        return np.asarray((jaxlie.SE3(self.z0) @ jaxlie.SE3.exp(self.theta[:6])).wxyz_xyz)

    @property
    def flange_from_probe(self) -> np.ndarray:
        return np.asarray((jaxlie.SE3(self.x0) @ jaxlie.SE3.exp(self.theta[6:12])).wxyz_xyz)

    def predict(self, series: PoseSeries) -> np.ndarray:
        """camera←probe `(N, 7)` (``wxyz_xyz``, m) this fit predicts for `series`' poses."""
        w = np.ones((series.n, 6))
        data = pose_data(
            self.z0, self.x0, series.joints, series.drift_variable, series.measured, w, False
        )
        return np.asarray(predict_probe_poses(jnp.asarray(self.theta), data))

    def effect_values(self) -> dict[str, list]:
        out = {}
        for e in self.estimated:
            name, idx = parse_effect_spec(e)
            v = self.theta[_SL[name]]
            out[e] = (
                v if name not in ("joint_harmonic", "joint_map") or idx is None else v[idx]
            ).tolist()
        return out

    def parameters(self) -> dict[str, tuple[float, float]]:
        """Estimated effect parameters {name: (value, σ)} in SI units (the maps' knots
        apart: `maps`)."""
        names = parameter_names()
        return {
            names[i]: (float(self.theta[i]), float(self.sigma[i]))
            for i in range(12, N_PARAMS)
            if self.free[i]
        }

    def maps(self) -> dict[int, dict[str, np.ndarray]]:
        """The estimated joint angle error maps, {joint (1-based): {"knots": angles [rad],
        "value": [rad], "sigma": posterior 1σ [rad], "estimated": bool per knot (False:
        held at zero, far from the data)}}, over the whole revolution."""
        if not self.has_maps or not np.any(self.free[N_PARAMS:]):
            return {}
        out = {}
        block = self.theta[_SL["joint_map"]].reshape(6, MAP_KNOTS)
        sig = self.sigma_model[_SL["joint_map"]].reshape(6, MAP_KNOTS)
        free = self.free[_SL["joint_map"]].reshape(6, MAP_KNOTS)
        knots = np.arange(MAP_KNOTS) * 2 * np.pi / MAP_KNOTS
        for j in range(6):
            if free[j].any():
                out[j + 1] = {
                    "knots": knots,
                    "value": block[j],
                    "sigma": np.where(free[j], sig[j], np.nan),
                    "estimated": free[j],
                }
        return out

    def summary(self, noise_m: float = 0.0) -> dict[str, float]:
        return error_summary(self.position_error, self.angle_error, noise_m)


def map_knots_supported(series: PoseSeries) -> np.ndarray:
    """`(N_MAP,)` bool: the knots of every joint's map near the series' angles
    (`robtraj.model.map_support`); the others are held at zero, their prior mean."""
    return np.concatenate([map_support(series.joints[:, j], MAP_KNOTS) for j in range(6)])


def _free_mask(
    estimate: Sequence[str],
    rigid: Sequence[str] = ("camera", "probe"),
    series: PoseSeries | None = None,
    maps: bool = False,
) -> np.ndarray:
    free = np.zeros(n_params(maps), bool)
    if "camera" in rigid:
        free[:6] = True
    if "probe" in rigid:
        free[6:12] = True
    for spec in estimate:
        name, idx = parse_effect_spec(spec)
        sl = _SL[name]
        if idx is None:
            free[sl] = True
        else:
            free[sl.start + np.asarray(idx)] = True
    free[POSE_REDUNDANT] = False
    if maps and series is not None:
        free[_SL["joint_map"]] &= map_knots_supported(series)
    return free


def _weights(series: PoseSeries, block_sigma: tuple[float, float]) -> np.ndarray:
    """`(N, 6)` weights 1/variance (see the module docstring)."""
    sp, sr = block_sigma
    var = np.empty((series.n, 6))
    var[:, :3] = sp**2
    var[:, 3:] = sr**2
    if series.std is not None:
        std = np.nan_to_num(np.asarray(series.std, float))
        var[:, :3] += np.mean(std[:, :3] ** 2, 1, keepdims=True)
        var[:, 3:] += np.mean(std[:, 3:] ** 2, 1, keepdims=True)
    return 1.0 / var


def _block_sigma(r: np.ndarray, series: PoseSeries) -> tuple[float, float]:
    """Unexplained σ per block (position [m], rotation [rad]) beyond the tracker's std."""
    out = []
    for blk in (slice(0, 3), slice(3, 6)):
        v = float(np.mean(r[:, blk] ** 2))
        if series.std is not None:
            v -= float(np.mean(np.nan_to_num(series.std[:, blk]) ** 2))
        out.append(math.sqrt(max(v, 1e-16)))
    return out[0], out[1]


def linearise(theta: np.ndarray, data: PoseData, label: np.ndarray) -> Linearisation:
    """The linearisation of the pose model of `data` at `theta`, per region `label`."""
    members = jnp.asarray(group_members(label))
    h_g, b_g, c_g, r, j = (
        np.asarray(a) for a in pose_group_terms(jnp.asarray(theta), data, members)
    )
    return Linearisation(
        theta=np.asarray(theta, float),
        label=np.asarray(label),
        h=h_g.sum(0),
        b=b_g.sum(0),
        cost=float(c_g.sum()),
        h_g=h_g,
        b_g=b_g,
        r=r,
        j=j,
        map_index=np.asarray(data.map_index),
        map_weight=np.asarray(data.map_weight),
        offset=POSE_MAP_OFFSET,
    )


def structure_normal(theta, z0, x0, series: PoseSeries, w: np.ndarray) -> np.ndarray:
    """The data's normal matrix `(P, P)` at the effects' zero with `theta`'s rigid
    transforms (no prior), for identifiability: there a null direction of the model's
    structure is exact (parallel axes, say), where at an estimate the estimated effects
    (a twist of a parallel axis) break it by rounding-size amounts."""
    p = theta.shape[0]
    at = jnp.asarray(np.where(np.arange(p) < 12, theta, 0.0))
    prior = zero_map_prior() if p > N_PARAMS else None
    return np.asarray(normal_at(pose_normal, at, _data(z0, x0, series, w, False, prior))[0])


def _data(
    z0, x0, series: PoseSeries, w: np.ndarray, rigid_only: bool, prior: GaussianPrior | None = None
) -> PoseData:
    return pose_data(
        z0,
        x0,
        series.joints,
        series.drift_variable,
        series.measured,
        w,
        rigid_only,
        prior,
    )


#: knots the prior determines most took ~10 steps
PRIOR_DAMPING = 1e-4


def _solve(theta, free, z0, x0, series, w, prior=None, max_iter=50):
    """The engine on the weighted residuals (and the prior) over the `free` parameters."""
    if (prior is None or not prior.size) and theta.shape[0] > N_PARAMS:
        prior = zero_map_prior()
    data = _data(z0, x0, series, w, bool(np.all(np.flatnonzero(free) < 12)), prior)
    sol = solve(
        pose_normal,
        data,
        theta,
        free,
        n_residuals=6 * series.n,
        max_steps=max_iter,
        damping=PRIOR_DAMPING if data.prior.size else None,
    )
    return sol, data


@serial_blas
def fit_poses(
    series: PoseSeries,
    *,
    estimate: Sequence[str] = (),
    init: PoseFit | None = None,
    fixed: PoseFit | None = None,
    rigid: Sequence[str] = ("camera", "probe"),
    block_sigma: tuple[float, float] | None = None,
    map_prior: tuple[float, float] | None = None,
    max_iter: int = 50,
    structure: np.ndarray | None = None,
    maps_layout: bool = False,
) -> PoseFit:
    """Calibrate `series` at pose level (see the module docstring).

    - `estimate`: effects to fit besides the rigid transforms (`robtraj.estimate.POSE_EFFECTS`, the
      dictionary's joint harmonics and joint angle error maps; ``joint_map``: every
      joint's map).
    - `init`: start from this fit of the same series (its θ and start transforms).
    - `fixed`: a fit of *another* series whose effects are frozen here (cross-series
      prediction); only the rigid transforms named in `rigid` are refitted.
    - `rigid`: which rigid transforms are free: ``"camera"`` (camera←base) and/or
      ``"probe"`` (flange←probe).
    - `block_sigma`: unexplained σ (position [m], rotation [rad]) used for the
      weights; default: estimated from a nominal rigid fit of this series.
    - `map_prior`: (σ_f, ℓ) [rad] of the maps' prior (`robtraj.model.map_precision`);
      default the terms' own (`Term.precision`). A map's knots far from the series'
      angles are held at zero, their prior mean (`map_knots_supported`).
    - `structure`: the data's normal matrix at the effects' zero (no prior;
      `structure_normal`), where the caller has it (a selection: at its nominal fit's
      rigid transforms); default: at the start's rigid transforms.
    - `maps_layout`: θ in the layout with the maps' block even where no map is
      estimated (held at zero), so that the fit shares the compiled normal equations of
      the fits that estimate maps (a workflow whose candidates include them).
    """
    maps = (
        maps_layout
        or uses_maps(estimate)
        or any(f is not None and f.has_maps for f in (init, fixed))
    )
    p = n_params(maps)
    if init is not None:
        theta, z0, x0 = _resized(init.theta, p), init.z0, init.x0
    else:
        z0, x0 = series.start
        theta = np.zeros(p)
    if fixed is not None:
        theta[12:] = _resized(fixed.theta, p)[12:]
        if "probe" not in rigid:
            # same probe mounting: carry the source's flange←probe over
            x0 = fixed.flange_from_probe
            theta[6:12] = 0.0
    free = _free_mask(estimate, rigid, series, maps)
    prior = map_prior_of(estimate, map_prior) if fixed is None else no_prior()
    if block_sigma is None:
        # block weights from the residuals of a first, rigid-only pass
        sol0, d0 = _solve(
            theta.copy(),
            _free_mask((), rigid, maps=maps),
            z0,
            x0,
            series,
            _weights(series, (1e-3, 1e-3)),
        )
        theta = sol0.theta
        block_sigma = _block_sigma(np.asarray(pose_residual(jnp.asarray(theta), d0)), series)
    w = _weights(series, block_sigma)
    if np.any(free[12:]):
        # identifiability of the model's structure (`structure_normal`)
        if structure is None:
            structure = structure_normal(theta, z0, x0, series, w)
        free, ident = identifiable(structure + prior.dense(p), free)
        theta = np.where(free | (np.arange(p) < 12), theta, 0.0)
    else:
        ident = {"dropped": [], "condition_number": float("nan")}
    if fixed is not None:
        theta[12:] = _resized(fixed.theta, p)[12:]
    sol, data = _solve(theta, free, z0, x0, series, w, prior, max_iter)
    theta = sol.theta
    h = np.asarray((sol.normal or normal_at(pose_normal, jnp.asarray(theta), data))[0])
    n_res = 6 * series.n
    lam = data.prior.dense(p)
    prior_cost = float(theta @ lam @ theta)
    chi2 = sol.cost - prior_cost
    cov_unit, rank = covariance(h, free)
    # effective parameter count tr((H_data + Λ)⁺ H_data): the rank without a prior
    p_eff = float(np.sum(cov_unit * (h - lam))) if data.prior.size else float(rank)
    cov = cov_unit * (chi2 / max(1.0, n_res - p_eff))
    sigma = sigma_of(cov, free)

    def robust():
        # one linearisation for both: the Jacobian does not depend on the regions
        lin = linearise(theta, data, regions(series))
        flat = free & ~prior_entries
        field = _model_error_field(lin, data, free, flat, series, h)
        cov_f = np.zeros_like(h)
        cov_f[np.ix_(flat, flat)] = field.covariance * (chi2 / max(1.0, n_res - p_eff))
        return {
            "jackknife": sigma_of(_region_jackknife(lin, data, free), free),
            "field": sigma_of(cov_f, free),
            "model_error": field.as_dict(),
        }

    pred = np.asarray(predict_probe_poses(jnp.asarray(theta), data))
    pos, ang = pose_errors(pred, series.measured)
    prior_entries = np.zeros(p, bool)
    prior_entries[np.asarray(data.prior.index)] = True
    return PoseFit(
        series=series.name,
        estimated=tuple(estimate) if fixed is None else fixed.estimated,
        theta=theta,
        z0=np.asarray(z0),
        x0=np.asarray(x0),
        free=free,
        sigma_model=sigma,
        chi2=chi2,
        n_residuals=n_res,
        block_sigma=tuple(float(b) for b in block_sigma),
        identifiability=ident,
        position_error=pos,
        angle_error=ang,
        iterations=sol.steps,
        converged=sol.converged,
        effective_parameters=p_eff,
        map_prior=(
            None
            if fixed is not None or not map_terms_of(estimate)
            else tuple(map_prior)
            if map_prior is not None
            else (MAP_SIGMA_F, MAP_LENGTH)
        ),
        prior_entries=prior_entries,
        covariance=cov[:N_PARAMS, :N_PARAMS],
        _robust=robust if fixed is None else None,
    )


def frozen_fit(
    theta: np.ndarray, z0: np.ndarray, x0: np.ndarray, estimated: tuple[str, ...] = ()
) -> PoseFit:
    """A model given by its θ (`parameter_names` layout) and start transforms, not
    fitted to any series: the `fixed` source of a prediction (`fit_poses`)."""
    p = theta.size
    empty = np.zeros(0)
    return PoseFit(
        series="",
        estimated=estimated,
        theta=np.asarray(theta, float),
        z0=np.asarray(z0, float),
        x0=np.asarray(x0, float),
        free=np.zeros(p, bool),
        sigma_model=np.full(p, np.nan),
        chi2=float("nan"),
        n_residuals=0,
        block_sigma=(float("nan"), float("nan")),
        identifiability={"dropped": []},
        position_error=empty,
        angle_error=empty,
        iterations=0,
        converged=True,
    )


def marginal(h: np.ndarray, map_free: np.ndarray) -> np.ndarray:
    """The normal matrix of θ's entries before the maps with the free map knots
    (`map_free`, `(P,)` bool, True on knots only) marginalised: the Schur complement
    ``H_dd − H_dm H_mm⁻¹ H_md``, `(N_PARAMS, N_PARAMS)` (`h` with the prior, which makes
    the knots' block positive definite)."""
    knots = np.flatnonzero(map_free[N_PARAMS:]) + N_PARAMS
    rest = np.arange(N_PARAMS)
    if not knots.size:
        return h[np.ix_(rest, rest)]
    cross = h[np.ix_(knots, rest)]
    return h[np.ix_(rest, rest)] - cross.T @ solve_scaled(h[np.ix_(knots, knots)], cross)


def identifiable(
    h: np.ndarray, free: np.ndarray, schur: np.ndarray | None = None
) -> tuple[np.ndarray, dict[str, Any]]:
    """`robtraj.estimate.identifiability` of θ's effect entries (the rigid transforms are
    never fixed; the UR10's degeneracies fixed in the order `FIX_PREFERENCE`) from the
    normal matrix `h` with the prior. The free knots of the maps are determined by their
    prior: they are marginalised (`marginal`; `schur` if the caller has it) and the rest
    is analysed, a matrix of the effects' size instead of a thousand knots'."""
    droppable = np.arange(N_PARAMS) >= 12
    names = parameter_names()
    if h.shape[0] == N_PARAMS:
        return identifiability(h, names, free, droppable, prefer=FIX_PREFERENCE)
    schur = marginal(h, free) if schur is None else schur
    kept, ident = identifiability(schur, names, free[:N_PARAMS], droppable, prefer=FIX_PREFERENCE)
    return np.concatenate([kept, free[N_PARAMS:]]), ident


def _resized(theta: np.ndarray, p: int) -> np.ndarray:
    """θ in a layout of `p` entries (the map block added as zeros, or left out)."""
    out = np.zeros(p)
    k = min(p, theta.size)
    out[:k] = theta[:k]
    return out


def regions(series: PoseSeries, n: int = REGIONS) -> np.ndarray:
    """`(N,)` region of every pose in joint space (k-means on the first five joints,
    seeded; at most `n` regions, labels ``0..G−1`` without empty ones): poses near each
    other share the model's error, poses far apart much less."""
    g = min(n, series.n // 2)
    if g < 2:
        return np.zeros(series.n, int)
    _, label = kmeans2(np.asarray(series.joints)[:, :5], g, seed=0, minit="++")
    _, label = np.unique(label, return_inverse=True)
    return label


@serial_blas
def _region_jackknife(lin: Linearisation, data: PoseData, free) -> np.ndarray:
    """The delete-one-region jackknife (`robtraj.estimate.jackknife_covariance`, the
    formula of `robust_covariance`) with the poses grouped into the `regions` of joint
    space of `lin`'s labels, each deletion one Gauss–Newton step from the estimate, the
    maps' knots eliminated first (`_pose_cv.RegionSystems`)."""
    p = lin.theta.size
    if lin.label.max() < 1:
        return np.full((p, p), np.nan)
    prior = data.prior.dense(p) if data.prior.size else None
    return jackknife_covariance(RegionSystems(lin, prior, free).steps(free)[:-1])


def _model_error_field(
    lin: Linearisation, data: PoseData, free, flat, series: PoseSeries, h
) -> ModelErrorField:
    """`robtraj.estimate.field_covariance` of the `flat` parameters (free, without a
    prior), the model error a field over the six joint angles [rad] whose relative
    amplitude per pose follows its weights (a pose with a larger tracker std sees the same
    field smaller in whitened units); `lin` the linearisation at the estimate, `h` the
    posterior normal matrix."""
    columns = np.flatnonzero(free)
    sqrt_w = np.asarray(data.sqrt_w)
    rows = jacobian_rows(
        lin.j, sqrt_w, lin.offset, lin.map_index, lin.map_weight, lin.theta.size - N_PARAMS, columns
    )
    amplitude = np.exp(np.mean(np.log(sqrt_w / np.median(sqrt_w, 0)), 1))
    return field_covariance(
        h[np.ix_(columns, columns)],
        rows,
        (lin.r * sqrt_w).T,
        np.asarray(series.joints),
        amplitude,
        flat=flat[columns],
    )


def cross_predict(
    source: PoseFit, target: PoseSeries, rigid: Sequence[str] = ("camera", "probe")
) -> PoseFit:
    """Predict `target` with `source`'s effects frozen; refit only the `rigid` transforms."""
    return fit_poses(target, fixed=source, rigid=rigid)
