"""Pose-level fit of a UR10 to laser-tracker probe poses: the parameter layout, the
measurement model through `robtraj.model`, its normal equations and weights; solved,
with identifiability and covariance, by the package's one engine
(`robtraj.estimate.solve`; see `robtraj.analysis.real_data` for the model)."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array
from scipy.cluster.vq import kmeans2

from .._blas import serial_blas
from .._errors import UserError
from ..estimate import (
    GaussianPrior,
    ModelErrorField,
    QuotedSigma,
    composed,
    covariance,
    field_covariance,
    identifiability,
    jackknife_covariance,
    no_prior,
    normal_at,
    quoted_sigma,
    sigma_of,
    solve,
    term_prior,
)
from ..model import (
    HARMONICS,
    MAP_KNOTS,
    MAP_LENGTH,
    MAP_SIGMA_F,
    Effects,
    camera_from_base_at,
    dh_corrections,
    effect_component_names,
    flange_jacobian,
    forward_kinematics,
    joint_maps,
    map_active,
    map_precision,
    map_support,
    redundant_link_parameters,
    ur10,
)
from ._pose_cv import Linearisation, RegionSystems, solve_scaled
from ._pose_normal import group_members, jacobian_rows, map_index, normal_terms
from ._pose_series import PoseSeries
from ._quat import rotation_angle

#: order of the parameter vector after the 12 rigid parameters
_EFFECT_ORDER = (
    "joint_offset",
    "link_length",
    "link_twist",
    "joint_compliance",
    "thermal_drift",
    "tracker_scale",
    "joint_harmonic",
    "joint_map",
)
#: the dictionary's joint-angle harmonics, in the order of the `joint_harmonic` block
HARMONIC_TERMS = tuple(f"joint{j + 1}_harmonic{h}" for j in range(6) for h in HARMONICS)
#: the dictionary's joint angle error maps, in the order of the `joint_map` block (θ
#: holds that block only in a fit that estimates or carries a map: `n_params`)
MAP_TERMS = joint_maps(6)
_TANGENT = ("tx", "ty", "tz", "rx", "ry", "rz")
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


def _effect_sizes(n_joints: int = 6) -> dict[str, int]:
    return {
        "joint_offset": n_joints,
        "link_length": 2 * n_joints,
        "link_twist": 2 * n_joints,
        "joint_compliance": n_joints,
        "thermal_drift": 3,
        "tracker_scale": 1,
        "joint_harmonic": 2 * len(HARMONICS) * n_joints,
        "joint_map": MAP_KNOTS * n_joints,
    }


def parameter_names(n_joints: int = 6, maps: bool = False) -> list[str]:
    """Names of θ's entries; with `maps`, the joint angle error maps' knots at the end
    (``joint2_map.k017``)."""
    names = [f"camera_from_base.{t}" for t in _TANGENT]
    names += [f"flange_from_probe.{t}" for t in _TANGENT]
    zeros = Effects.zeros(n_joints)
    for name in _EFFECT_ORDER[:-2]:
        names += effect_component_names(name, np.shape(getattr(zeros, name)))
    for t in HARMONIC_TERMS:
        names += effect_component_names(t, (2,))
    if maps:
        for t in MAP_TERMS:
            names += effect_component_names(t, (MAP_KNOTS,))
    return names


def _slices(n_joints: int = 6) -> dict[str, slice]:
    out, k = {}, 12
    for name, size in _effect_sizes(n_joints).items():
        out[name] = slice(k, k + size)
        k += size
    return out


#: θ entries without the maps (every fit's θ begins with them)
N_PARAMS = len(parameter_names())
#: entries of the map block
N_MAP = MAP_KNOTS * 6
_SL = _slices()
#: the joint offsets' columns: the joints' turn columns, which the maps' columns scale
_OFFSET = (_SL["joint_offset"].start, _SL["joint_offset"].stop)
#: θ entries never estimated (Hayati's tilt of non-parallel axes, the last link's axis)
_REDUNDANT = [parameter_names().index(n) for n in redundant_link_parameters(ur10())]


def n_params(maps: bool) -> int:
    """The length of θ, with or without the map block."""
    return N_PARAMS + (N_MAP if maps else 0)


def _has_maps(theta) -> bool:
    return theta.shape[0] > N_PARAMS


def _effects_of(theta) -> Effects:
    e = Effects.zeros(6)
    terms = {
        t: theta[_SL["joint_harmonic"]][2 * k : 2 * k + 2] for k, t in enumerate(HARMONIC_TERMS)
    }
    if _has_maps(theta):
        m = theta[_SL["joint_map"]].reshape(6, MAP_KNOTS)
        terms.update({t: m[k] for k, t in enumerate(MAP_TERMS)})
    return dataclasses.replace(
        e,
        joint_offset=theta[_SL["joint_offset"]],
        link_length=theta[_SL["link_length"]].reshape(6, 2),
        link_twist=theta[_SL["link_twist"]].reshape(6, 2),
        joint_compliance=theta[_SL["joint_compliance"]],
        thermal_drift=theta[_SL["thermal_drift"]],
        tracker_scale=theta[_SL["tracker_scale"]][0],
        terms=terms,
    )


def _harmonics(joints) -> Array:
    """`(N, joints, 2·H)`: ``[sin(h·q), cos(h·q)]`` per joint and harmonic h."""
    hq = joints[..., None] * jnp.asarray(HARMONICS, joints.dtype)
    return jnp.stack([jnp.sin(hq), jnp.cos(hq)], -1).reshape(*joints.shape, -1)


def _flange(eff: Effects, joints, torque) -> jaxlie.SE3:
    """base←flange: `robtraj.model.flange_poses` for static poses (no backlash), with the
    gravity torques of the nominal link-mass model precomputed (they do not depend on
    the parameters; `flange_poses` recomputes them inside every Jacobian column)."""
    robot = ur10()
    dh_delta, tilt = dh_corrections(robot, eff)
    q = _joint_angles(eff, joints, torque)
    return jax.vmap(lambda qq: forward_kinematics(robot, qq, dh_delta, tilt))(q)


def _joint_angles(eff: Effects, joints, torque) -> Array:
    """`(N, joints)` angles the links take: the log plus offsets, gravity deflection, the
    harmonics and the maps (`robtraj.model.effective_joints` for static poses)."""
    return (
        joints
        + eff.joint_offset
        + eff.joint_compliance * torque
        + _harmonic_error(eff, joints)
        + _map_error(eff, joints)
    )


def _harmonic_error(eff: Effects, joints) -> Array:
    """`(N, joints)` joint-angle error of the dictionary's harmonics in `eff` [rad]."""
    c = jnp.stack([eff.terms[t] for t in HARMONIC_TERMS]).reshape(joints.shape[-1], -1)
    return jnp.einsum("njk,jk->nj", _harmonics(joints), c)


def _map_error(eff: Effects, joints) -> Array:
    """`(N, joints)` joint-angle error of the maps in `eff` [rad], from each angle's two
    active knots (zero without maps)."""
    if MAP_TERMS[0] not in eff.terms:
        return jnp.zeros_like(joints)
    c = jnp.stack([eff.terms[t] for t in MAP_TERMS])  # (joints, knots)
    idx, w = map_active(joints, MAP_KNOTS)
    return jnp.sum(w * c[jnp.arange(joints.shape[-1])[None, :, None], idx], -1)


def _predict(theta, z0, x0, joints, drift, torque):
    """camera←probe predicted `(N, 7)` for the parameter vector `theta`."""
    eff = _effects_of(theta)
    z = jaxlie.SE3(z0) @ jaxlie.SE3.exp(theta[:6])
    x = jaxlie.SE3(x0) @ jaxlie.SE3.exp(theta[6:12])
    flange = _flange(eff, joints, torque)
    cam = camera_from_base_at(z, eff, drift)
    pose = cam @ flange @ x
    pos = (1.0 + eff.tracker_scale) * pose.translation()
    return jnp.concatenate([pose.rotation().wxyz, pos], -1)


def _raw_residual(theta, z0, x0, joints, drift, torque, measured):
    """`(N, 6)`: position error [m] and rotation vector [rad] of measured⁻¹·predicted."""
    pred = _predict(theta, z0, x0, joints, drift, torque)
    dp = pred[:, 4:] - measured[:, 4:]
    dr = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        measured[:, :4], pred[:, :4]
    )
    return jnp.concatenate([dp, dr], -1)


_predict_jit = jax.jit(lambda *a: _predict(*a))

#: θ entries that act on the flange pose through the kinematics, and the rest
_KINEMATIC = np.r_[
    _SL["joint_offset"],
    _SL["link_length"],
    _SL["link_twist"],
    _SL["joint_compliance"],
    _SL["joint_harmonic"],
]
_GLOBAL = np.setdiff1d(np.arange(N_PARAMS), _KINEMATIC)


def _jacobian(theta, z0, x0, joints, drift, torque, measured):
    """The residual `(N, 6)` and its Jacobian `(N, 6, N_PARAMS)` in the entries before the
    maps by the chain rule: the kinematic columns are the flange twists of
    `robtraj.model.flange_jacobian` carried through the residual's derivative in a
    flange twist (6 tangents per pose), the others forward-mode (16 tangents) — not
    forward-mode through the kinematics. A map's column is its joint's offset column
    times the hat value (`_pose_normal`)."""
    robot = ur10()
    eff = _effects_of(theta)
    q = _joint_angles(eff, joints, torque)
    dh_delta, tilt = dh_corrections(robot, eff)
    flange, g = jax.vmap(lambda qq: flange_jacobian(robot, qq, dh_delta, tilt))(q)
    # (N, 6, joints, 5) → θ columns; a joint offset moves θ, a compliance τ·θ, a
    # harmonic sin(h·q)·θ or cos(h·q)·θ
    n = q.shape[0]
    kin = jnp.concatenate(
        [
            g[..., 0],
            g[..., 1:3].reshape(n, 6, -1),
            g[..., 3:5].reshape(n, 6, -1),
            g[..., 0] * torque[:, None, :],
            (g[..., 0, None] * _harmonics(joints)[:, None]).reshape(n, 6, -1),
        ],
        -1,
    )

    def residual(theta_global, xi):
        t = theta.at[_GLOBAL].set(theta_global)
        e = _effects_of(t)
        f = jax.vmap(lambda a, b: (jaxlie.SE3.exp(a) @ jaxlie.SE3(b)).wxyz_xyz)(xi, flange.wxyz_xyz)
        shift = drift[:, None] * e.thermal_drift[None, :]
        return _rigid_residual(t[:12], z0, x0, f, shift, e.tracker_scale, measured)

    xi0 = jnp.zeros((n, 6), theta.dtype)
    tg = theta[_GLOBAL]
    r = residual(tg, xi0)
    j_global = jax.jacfwd(residual)(tg, xi0)  # (N, 6, 16)
    # each pose's residual depends on its own twist only: 6 tangents, all poses at once
    j_xi = jax.vmap(
        lambda dx: jax.jvp(lambda e: residual(tg, e), (xi0,), (jnp.broadcast_to(dx, (n, 6)),))[1],
        out_axes=-1,
    )(jnp.eye(6, dtype=theta.dtype))  # (N, 6, 6)
    j = jnp.zeros((n, 6, N_PARAMS), r.dtype)
    j = j.at[..., _GLOBAL].set(j_global)
    j = j.at[..., _KINEMATIC].set(jnp.einsum("nrk,nkp->nrp", j_xi, kin))
    return r, j


# ----------------------------------------------------------------------------- errors


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
        args = (self.theta, self.z0, self.x0, series.joints, series.drift_variable, series.torque)
        return np.asarray(_predict_jit(*(jnp.asarray(a) for a in args)))

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


def parse_effect_spec(spec: str) -> tuple[str, list[int] | None]:
    """``"joint_compliance"`` → all its parameters; ``"joint_compliance[1,2]"`` → only
    those elements (e.g. the joints that carry the arm's weight); a dictionary term
    (``joint2_harmonic1``, ``joint2_map``) → its entries of the harmonic or map block;
    ``"joint_map"`` → every joint's map."""
    if spec in HARMONIC_TERMS:
        k = HARMONIC_TERMS.index(spec)
        return "joint_harmonic", [2 * k, 2 * k + 1]
    if spec in MAP_TERMS:
        k = MAP_TERMS.index(spec)
        return "joint_map", list(range(k * MAP_KNOTS, (k + 1) * MAP_KNOTS))
    name, _, rest = spec.partition("[")
    if name not in _SL:
        raise UserError(
            f"effect {name!r} is not fitted at pose level (choose from {_EFFECT_ORDER}, "
            "a joint harmonic of the dictionary, e.g. joint2_harmonic1, or a joint angle "
            "error map, e.g. joint2_map)"
        )
    if not rest:
        return name, None
    try:
        idx = [int(v) for v in rest.rstrip("]").split(",")]
    except ValueError:
        raise UserError(f"bad effect {spec!r}: expected NAME[i,j,...]") from None
    size = _SL[name].stop - _SL[name].start
    if any(i < 0 or i >= size for i in idx):
        raise UserError(f"bad effect {spec!r}: indices must lie in 0..{size - 1}")
    return name, idx


def uses_maps(estimate: Sequence[str]) -> bool:
    """Whether the effects `estimate` include a joint angle error map."""
    return any(parse_effect_spec(e)[0] == "joint_map" for e in estimate)


def map_terms_of(estimate: Sequence[str]) -> tuple[str, ...]:
    """The map terms (``joint2_map``) among the effects `estimate`."""
    out = set()
    for e in estimate:
        name, idx = parse_effect_spec(e)
        if name == "joint_map":
            joints = range(6) if idx is None else {i // MAP_KNOTS for i in idx}
            out.update(MAP_TERMS[j] for j in joints)
    return tuple(t for t in MAP_TERMS if t in out)


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
    free[_REDUNDANT] = False
    if maps and series is not None:
        free[_SL["joint_map"]] &= map_knots_supported(series)
    return free


def map_prior_of(
    estimate: Sequence[str], map_prior: tuple[float, float] | None = None
) -> GaussianPrior:
    """The Gaussian prior of the maps among `estimate` (`robtraj.estimate.term_prior`):
    each term's own precision, or that of `map_prior` = (σ_f, ℓ) [rad]."""
    terms = map_terms_of(estimate)
    if not terms:
        return no_prior()
    blocks = [(t, _SL["joint_map"].start + MAP_TERMS.index(t) * MAP_KNOTS) for t in terms]
    precisions = None
    if map_prior is not None:
        lam = map_precision(MAP_KNOTS, *map_prior)
        precisions = {t: lam for t in terms}
    return term_prior(blocks, precisions)


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


@jax.jit
def _effect_part(theta, joints, drift, torque):
    """What the effects contribute, for the rigid-only fast path: base←flange
    (``wxyz_xyz``), the thermal shift of camera←base `(N, 3)` and the scale."""
    eff = _effects_of(theta)
    flange = _flange(eff, joints, torque).wxyz_xyz
    return flange, drift[:, None] * eff.thermal_drift[None, :], eff.tracker_scale


def _rigid_residual(t12, z0, x0, flange, shift, scale, measured):
    z = jaxlie.SE3(z0) @ jaxlie.SE3.exp(t12[:6])
    x = jaxlie.SE3(x0) @ jaxlie.SE3.exp(t12[6:])
    pose = jax.vmap(lambda f: z @ jaxlie.SE3(f) @ x)(flange)
    pos = (1.0 + scale) * (pose.translation() + shift)
    dp = pos - measured[:, 4:]
    dr = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        measured[:, :4], pose.rotation().wxyz
    )
    return jnp.concatenate([dp, dr], -1)


class PoseData(eqx.Module):
    """One series as the engine's ``data``: start transforms z0, x0 (``wxyz_xyz``),
    joints, drift variable, gravity torques, measured poses, ``sqrt(w)`` `(N, 6)`, the
    maps' active knots at the joints (`_pose_normal.map_index`) and the Gaussian prior
    of the estimated terms that carry one. `rigid_only`: only the 12 rigid parameters
    are differentiated (nominal fits, cross-series refits); the effects are evaluated
    once."""

    z0: Any
    x0: Any
    joints: Any
    drift: Any
    torque: Any
    measured: Any
    sqrt_w: Any
    map_index: Any
    map_weight: Any
    prior: GaussianPrior
    rigid_only: bool = eqx.field(static=True, default=False)


def _pose_residual(theta, d: PoseData):
    """`(N, 6)` unweighted residual (position [m], rotation vector [rad])."""
    if d.rigid_only:
        return _rigid_residual(
            theta[:12], d.z0, d.x0, *_effect_part(theta, d.joints, d.drift, d.torque), d.measured
        )
    return _raw_residual(theta, d.z0, d.x0, d.joints, d.drift, d.torque, d.measured)


_pose_residual_jit = eqx.filter_jit(_pose_residual)


@composed
def pose_normal(theta, d: PoseData):
    """``(H, b, cost)`` of the weighted pose residuals plus the prior (`robtraj.estimate.
    solve`): the dense columns' Jacobian of a few thousand poses is small enough to
    form, the maps' block is accumulated from their active knots (`_pose_normal`). The
    Jacobian and the normal equations are two kernels (`composed`): `group_terms`
    shares the first."""
    if d.rigid_only:
        return _rigid_normal(theta, d)
    everyone = jnp.arange(d.joints.shape[0], dtype=jnp.int32)[None]
    h, b, c, _, _ = group_terms(theta, d, everyone)
    return _with_prior(h[0], b[0], c[0], theta, d.prior)


@jax.jit
def _rigid_normal(theta, d: PoseData):
    """`pose_normal` where only the 12 rigid parameters are differentiated."""
    p = theta.shape[0]
    part = _effect_part(theta, d.joints, d.drift, d.torque)

    def r12(t12):
        res = _rigid_residual(t12, d.z0, d.x0, *part, d.measured)
        return (d.sqrt_w * res).reshape(-1)

    r = r12(theta[:12])
    j = jax.jacfwd(r12)(theta[:12])
    h = jnp.zeros((p, p), r.dtype).at[:12, :12].set(j.T @ j)
    b = jnp.zeros(p, r.dtype).at[:12].set(-(j.T @ r))
    return d.prior.add_to(h, b, r @ r, theta[d.prior.index])


@jax.jit
def _with_prior(h, b, c, theta, prior: GaussianPrior):
    return prior.add_to(h, b, c, theta[prior.index])


_jacobian_jit = jax.jit(_jacobian)
_normal_terms_jit = jax.jit(normal_terms, static_argnames=("offset", "n_map"))


def group_terms(theta, d: PoseData, members):
    """Per group of poses (`members` `(G, M)`, `_pose_normal.group_members`): ``JᵀWJ`` `(G, P, P)`,
    ``−JᵀWr`` `(G, P)`, ``rᵀWr`` `(G,)`; and the unweighted residual `(N, 6)` and dense
    Jacobian `(N, 6, N_PARAMS)` (the maps' columns follow from it: `_pose_normal`)."""
    r, j = _jacobian_jit(theta, d.z0, d.x0, d.joints, d.drift, d.torque, d.measured)
    h, b, c = _normal_terms_jit(
        r,
        j,
        d.sqrt_w,
        offset=_OFFSET,
        index=d.map_index,
        weight=d.map_weight,
        n_map=theta.shape[0] - N_PARAMS,
        members=members,
    )
    return h, b, c, r, j


def linearise(theta: np.ndarray, data: PoseData, label: np.ndarray) -> Linearisation:
    """The linearisation of the pose model of `data` at `theta`, per region `label`."""
    members = jnp.asarray(group_members(label))
    h_g, b_g, c_g, r, j = (np.asarray(a) for a in group_terms(jnp.asarray(theta), data, members))
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
        offset=_OFFSET,
    )


@functools.cache
def zero_map_prior() -> GaussianPrior:
    """No prior, in the layout of the prior of every map (zero precision): normal
    equations without a prior share the compilation of those of a fit of the maps."""
    pr = map_prior_of(MAP_TERMS)
    return GaussianPrior(pr.index, jnp.zeros_like(pr.precision))


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
    idx, wt = map_index(jnp.asarray(series.joints), MAP_KNOTS)
    return PoseData(
        *(
            jnp.asarray(a)
            for a in (z0, x0, series.joints, series.drift_variable, series.torque, series.measured)
        ),
        sqrt_w=jnp.asarray(np.sqrt(w)),
        map_index=idx,
        map_weight=wt,
        prior=no_prior() if prior is None else prior,
        rigid_only=rigid_only,
    )


#: initial damping of a fit with a prior (`robtraj.estimate.solve`): the maps are linear
#: in their knots and the first Gauss–Newton step lands; at Optimistix's default the
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

    - `estimate`: effects to fit besides the rigid transforms (`_EFFECT_ORDER`, the
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
        block_sigma = _block_sigma(np.asarray(_pose_residual_jit(jnp.asarray(theta), d0)), series)
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

    pred = np.asarray(
        _predict_jit(jnp.asarray(theta), *(data.z0, data.x0, data.joints, data.drift, data.torque))
    )
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
