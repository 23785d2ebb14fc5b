"""The 6-DOF pose observation kind: static robot poses whose probe (the tool) a tracker
measures as camera←probe poses, e.g. a laser tracker's SMR on a UR10.

Its parameters are the bundle problem's global block g (`_calib_parameters`): the
camera←base and flange←tool corrections (jaxlie tangent order), then each effect of the
problem's space entry by entry — here `pose_space`, the library's effects a static pose
shows, every joint's harmonics of the dictionary and, where a fit carries them, the
joint angle error maps. So θ names and reads as g does (`theta_names`,
`apply_effects` on the nominal `Effects`), and a pose fit's values are a calibration's.
The residual of a pose is `(6,)`: the position error [m] in the tracker frame and the
rotation vector [rad] of measured⁻¹·predicted. The poses are a `BundleProblem`
without a constellation whose frames are its log's entries (`at_log`): prediction and
dense Jacobian are the bundle's (`probe_residual`, `probe_jacobian`: the closed-form
tool Jacobian), and the normal equations (`pose_normal`, per group of poses
`pose_group_terms`) take the maps' block from their active knots (`_pose_normal`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._errors import UserError
from ..model import (
    HARMONICS,
    MAP_KNOTS,
    Effects,
    flange_poses,
    joint_maps,
    map_precision,
    redundant_link_parameters,
    ur10,
)
from ._calib_parameters import theta_names
from ._calib_problem import (
    BundleProblem,
    Frames,
    apply_effects,
    probe_jacobian,
    probe_residual,
    tool_poses,
)
from ._pose_normal import map_index, normal_terms
from ._prior import GaussianPrior, no_prior, term_prior
from ._solve import composed

#: the library's effects a static pose shows, in θ's order after the rigid transforms
POSE_EFFECTS = (
    "joint_offset",
    "link_length",
    "link_twist",
    "joint_compliance",
    "thermal_drift",
    "tracker_scale",
)
#: the dictionary's joint-angle harmonics, in θ's order after `POSE_EFFECTS`
HARMONIC_TERMS = tuple(f"joint{j + 1}_harmonic{h}" for j in range(6) for h in HARMONICS)
#: the dictionary's joint angle error maps, last in θ (θ holds them only in a fit that
#: estimates or carries a map: `pose_n_params`)
MAP_TERMS = joint_maps(6)


def pose_space(maps: bool = False) -> tuple[str, ...]:
    """The effects of the pose problem in θ order (the bundle problem's ``free``)."""
    return (*POSE_EFFECTS, *HARMONIC_TERMS, *(MAP_TERMS if maps else ()))


def pose_parameter_names(maps: bool = False) -> list[str]:
    """Names of θ's entries (`theta_names` of `pose_space`); with `maps`, the joint angle
    error maps' knots at the end (``joint2_map.k017``)."""
    return theta_names(Effects.zeros(6), pose_space(maps), 0)[0]


def pose_slices() -> dict[str, slice]:
    """θ's entries of each library effect, of all harmonics (``joint_harmonic``) and of all
    maps (``joint_map``)."""
    groups = {t: "joint_harmonic" for t in HARMONIC_TERMS} | {t: "joint_map" for t in MAP_TERMS}
    out, k = {}, 12
    for name in pose_space(maps=True):
        size = int(np.size(Effects.zeros(6).get(name)))
        group = groups.get(name, name)
        start = out[group].start if group in out else k
        out[group] = slice(start, k + size)
        k += size
    return out


#: θ entries without the maps (every fit's θ begins with them)
N_PARAMS = len(pose_parameter_names())
#: entries of the map block
N_MAP = MAP_KNOTS * 6
_SL = pose_slices()
#: the joint offsets' columns: the joints' turn columns, which the maps' columns scale
MAP_OFFSET = (_SL["joint_offset"].start, _SL["joint_offset"].stop)
#: θ entries never estimated (Hayati's tilt of non-parallel axes, the last link's axis)
REDUNDANT = [pose_parameter_names().index(n) for n in redundant_link_parameters(ur10())]


def pose_n_params(maps: bool) -> int:
    """The length of θ, with or without the map block."""
    return N_PARAMS + (N_MAP if maps else 0)


def _has_maps(theta) -> bool:
    return theta.shape[0] > N_PARAMS


def pose_effects(theta) -> Effects:
    """The effects θ holds (the nominal model plus θ's entries after the rigid ones)."""
    return apply_effects(Effects.zeros(6), pose_space(_has_maps(theta)), theta[12:])


def pose_theta(effects: Effects, maps: bool = False) -> np.ndarray:
    """θ of the model `effects` with the rigid transforms at their start (zero): the
    values of `pose_space`'s effects, entry by entry (the inverse of `pose_effects`)."""
    values = [np.ravel(np.asarray(effects.get(n), float)) for n in pose_space(maps)]
    return np.concatenate([np.zeros(12), *values])


def _problem(theta, d: PoseData, kinematic: bool = True) -> tuple[Array, BundleProblem, Frames]:
    """The pose problem at θ as the bundle problem's parts: g (θ before the maps), the
    `BundleProblem` whose effects hold the maps' values (their columns are the sparse
    block of `_pose_normal`, not g's) and the poses as `Frames` of a log with one entry
    per pose (static: no motion, no clock)."""
    eff = Effects.zeros(6)
    if _has_maps(theta):
        eff = apply_effects(eff, MAP_TERMS, theta[N_PARAMS:])
    n = d.joints.shape[0]
    index = jnp.arange(n, dtype=theta.dtype)
    problem = BundleProblem(
        robot=ur10(),
        camera_from_base=d.z0,
        flange_from_tool=d.x0,
        constellation=jnp.zeros((0, 3), theta.dtype),
        normals=jnp.zeros((0, 3), theta.dtype),
        effects=eff,
        log_time=index,
        joints=d.joints,
        free=pose_space(False),
        kinematic=kinematic,
        at_log=True,
    )
    frames = Frames(
        time=index,
        direction=jnp.zeros_like(d.joints),
        moving=jnp.zeros_like(d.joints),
        drift=d.drift,
        measured=jnp.zeros((n, 0, 3), theta.dtype),
        sqrt_weight=jnp.zeros((n, 0), theta.dtype),
        base_from_flange=jnp.zeros((n, 7), theta.dtype),
    )
    return theta[:N_PARAMS], problem, frames


def _predict(theta, d: PoseData):
    """camera←probe predicted `(N, 7)` (``wxyz_xyz``, the tracker's scale applied)."""
    g, problem, frames = _problem(theta, d)
    tool, eff = tool_poses(g, problem, frames)
    pos = (1.0 + eff.tracker_scale) * tool.translation()
    return jnp.concatenate([tool.rotation().wxyz, pos], -1)


def _raw_residual(theta, d: PoseData):
    """`(N, 6)`: position error [m] and rotation vector [rad] of measured⁻¹·predicted
    (`probe_residual`)."""
    return probe_residual(*_problem(theta, d), d.measured)


#: camera←probe `(N, 7)` (``wxyz_xyz``, m) predicted for θ at the poses of `PoseData`
predict_probe_poses = eqx.filter_jit(_predict)


def _jacobian(theta, d: PoseData):
    """The residual `(N, 6)` and its Jacobian `(N, 6, N_PARAMS)` in the entries before the
    maps (`probe_jacobian`: the bundle problem's closed-form tool Jacobian). A map's
    column is its joint's offset column times the hat value (`_pose_normal`)."""
    return probe_jacobian(*_problem(theta, d), d.measured)


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
            f"effect {name!r} is not fitted at pose level (choose from {POSE_EFFECTS}, "
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


class PoseData(eqx.Module):
    """One series as the engine's ``data``: start transforms z0, x0 (``wxyz_xyz``),
    joints, drift variable, measured poses, ``sqrt(w)`` `(N, 6)`, the
    maps' active knots at the joints (`_pose_normal.map_index`) and the Gaussian prior
    of the estimated terms that carry one. `rigid_only`: only the 12 rigid parameters
    are differentiated (nominal fits, cross-series refits); the effects are evaluated
    once."""

    z0: Any
    x0: Any
    joints: Any
    drift: Any
    measured: Any
    sqrt_w: Any
    map_index: Any
    map_weight: Any
    prior: GaussianPrior
    rigid_only: bool = eqx.field(static=True, default=False)


def _held_effects(theta, d: PoseData) -> tuple[BundleProblem, Frames]:
    """The problem of the rigid-only fast path: θ's effects held, the flange poses
    evaluated once (`robtraj.model.flange_poses`)."""
    g, problem, frames = _problem(theta, d, kinematic=False)
    eff = apply_effects(problem.effects, problem.free, g[12:])
    flange = flange_poses(problem.robot, eff, d.joints, frames.direction)
    problem = dataclasses.replace(problem, effects=eff, free=())
    return problem, dataclasses.replace(frames, base_from_flange=flange.wxyz_xyz)


def _pose_residual(theta, d: PoseData):
    """`(N, 6)` unweighted residual (position [m], rotation vector [rad])."""
    if d.rigid_only:
        return probe_residual(theta[:12], *_held_effects(theta, d), d.measured)
    return _raw_residual(theta, d)


#: the unweighted residual `(N, 6)` of `PoseData` at θ (position [m], rotation vector [rad])
pose_residual = eqx.filter_jit(_pose_residual)


@composed
def pose_normal(theta, d: PoseData):
    """``(H, b, cost)`` of the weighted pose residuals plus the prior (`robtraj.estimate.
    solve`): the dense columns' Jacobian of a few thousand poses is small enough to
    form, the maps' block is accumulated from their active knots (`_pose_normal`). The
    Jacobian and the normal equations are two kernels (`composed`): `pose_group_terms`
    shares the first."""
    if d.rigid_only:
        return _rigid_normal(theta, d)
    everyone = jnp.arange(d.joints.shape[0], dtype=jnp.int32)[None]
    h, b, c, _, _ = pose_group_terms(theta, d, everyone)
    return _with_prior(h[0], b[0], c[0], theta, d.prior)


@jax.jit
def _rigid_normal(theta, d: PoseData):
    """`pose_normal` where only the 12 rigid parameters are differentiated."""
    p = theta.shape[0]
    r, j = probe_jacobian(theta[:12], *_held_effects(theta, d), d.measured)
    rw = (d.sqrt_w * r).reshape(-1)
    jw = (d.sqrt_w[..., None] * j).reshape(-1, 12)
    h = jnp.zeros((p, p), r.dtype).at[:12, :12].set(jw.T @ jw)
    b = jnp.zeros(p, r.dtype).at[:12].set(-(jw.T @ rw))
    return d.prior.add_to(h, b, rw @ rw, theta[d.prior.index])


@jax.jit
def _with_prior(h, b, c, theta, prior: GaussianPrior):
    return prior.add_to(h, b, c, theta[prior.index])


_jacobian_jit = eqx.filter_jit(_jacobian)
_normal_terms_jit = jax.jit(normal_terms, static_argnames=("offset", "n_map"))


def pose_group_terms(theta, d: PoseData, members):
    """Per group of poses (`members` `(G, M)`, `_pose_normal.group_members`): ``JᵀWJ`` `(G, P, P)`,
    ``−JᵀWr`` `(G, P)`, ``rᵀWr`` `(G,)`; and the unweighted residual `(N, 6)` and dense
    Jacobian `(N, 6, N_PARAMS)` (the maps' columns follow from it: `_pose_normal`)."""
    r, j = _jacobian_jit(theta, d)
    h, b, c = _normal_terms_jit(
        r,
        j,
        d.sqrt_w,
        offset=MAP_OFFSET,
        index=d.map_index,
        weight=d.map_weight,
        n_map=theta.shape[0] - N_PARAMS,
        members=members,
    )
    return h, b, c, r, j


@functools.cache
def zero_map_prior() -> GaussianPrior:
    """No prior, in the layout of the prior of every map (zero precision): normal
    equations without a prior share the compilation of those of a fit of the maps."""
    pr = map_prior_of(MAP_TERMS)
    return GaussianPrior(pr.index, jnp.zeros_like(pr.precision))


def pose_data(
    z0, x0, joints, drift, measured, w, rigid_only: bool, prior: GaussianPrior | None = None
) -> PoseData:
    """`PoseData` of poses at `joints` `(N, 6)` [rad] with their drift variable and
    measured camera←probe `(N, 7)` (``wxyz_xyz``), weighted by `w` `(N, 6)`."""
    idx, wt = map_index(jnp.asarray(joints), MAP_KNOTS)
    return PoseData(
        *(jnp.asarray(a) for a in (z0, x0, joints, drift, measured)),
        sqrt_w=jnp.asarray(np.sqrt(w)),
        map_index=idx,
        map_weight=wt,
        prior=no_prior() if prior is None else prior,
        rigid_only=rigid_only,
    )
