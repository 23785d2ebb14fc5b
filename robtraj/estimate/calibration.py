"""Bundle calibration (DESIGN section 5.4): camera, tool mount, constellation and effects.

Measurement model (section 5), for LED k at tracker frame t, through the one forward
model of `robtraj.model`::

    y_tk = camera_from_base · flange_pose(q(t + τ)) · flange_from_tool · p_k (+ effects) + noise

`fit` solves jointly for camera←base, flange←tool, the constellation p_k and any subset
of the `Effects` (`estimate=`), from every usable frame:

- **Parametrisation**: SE3 corrections in the tangent space around the current
  estimate (``T @ SE3.exp(δ)``, jaxlie order ``[tx, ty, tz, rx, ry, rz]``), never raw
  quaternions; effects additively.
- **Gauge** (tool frame): with probe data (`/probe`) the tool frame is the probed one
  (`gauge="probe"`: probe poses enter as extra residuals, the constellation is free).
  Without, `gauge="reference_constellation"`: the constellation correction
  ``p − p_ref`` is kept orthogonal to the six rigid motions of the reference
  constellation ``p_ref`` (the nominal `/tool/constellation`, or `init`'s) — zero mean
  translation and zero mean rotation — so the tool frame is the one in which the
  constellation best matches its reference; the TCP offset follows from the
  kinematics. `align_to_gauge` maps any (constellation, flange←tool) into this gauge.
- **Solver**: the package's one engine (`robtraj.estimate.solve`): Optimistix
  (Levenberg–Marquardt by default, or any `optx` least-squares solver via `solver=`) on
  the normal equations accumulated in chunks of frames (bounded memory, no Jacobian of
  the whole recording).
- **Initialisation** in closed form (`_calib_init`): weighted Procrustes tool poses on
  static dwells + Shah's robot-world/hand-eye solution.
- **Noise model**: by default every observation is weighted by the inverse of its
  variance from the recording's noise model (`robtraj.estimate.observation_noise`:
  emission angle from per-frame tool poses, distance and LED, from pair-distance second
  differences), independent of the robot model and of the start, so the weights do not
  absorb what the model misses; the covariance ``σ̂² (JᵀWJ)⁻¹`` (``σ̂² = χ²/(n − p)``) widens when the residual
  exceeds that noise.
- **Robust losses** (`robust="huber"|"cauchy"`): IRLS weights on the per-LED
  noise-normalised residual; frames whose residuals stand out are reported.
- **Identifiability**: null directions of the column-scaled normal matrix are named;
  confounded effect parameters are fixed at their initial values and reported
  (`robtraj.estimate.identifiability`).

Data flow, one module after the other: `_calib_data.prepare` (observations) →
`_calib_init` (closed-form start) → `_calib_problem` (parameters, residuals, normal
equations) → `_solve` (Optimistix) → `_uncertainty` (identifiability, covariance) →
`_calib_result` (the result). Beside it, on background threads (`_compile_ahead`): the
noise model (`_observation_noise`) while the observations are prepared and the start
computed, and the problem's structure and kernels (compiled for its shapes) meanwhile.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._errors import UserError
from ..model import (
    EFFECT_NAMES,
    LIBRARY,
    MOTION_THRESHOLD,
    Effects,
    effect_component_names,
    known_effects,
    redundant_link_parameters,
)
from ..recording import Pose, Recording
from . import _calib_problem as cp
from ._calib_data import CalibrationData, check, prepare
from ._calib_init import closed_form_start, dwells, pose_pairs, robot_world_hand_eye
from ._calib_problem import (
    BundleData,
    BundleProblem,
    Frames,
    bundle_normal,
    bundle_normal_clustered,
    residuals,
)
from ._calib_result import (
    READABLE_VERSIONS,
    SCHEMA_VERSION,
    CalibrationResult,
    _pose_of,
    _se3,
    _wxyz_xyz,
)
from ._clock import clock_effects
from ._compile_ahead import CompileAhead, in_background
from ._next_poses import next_poses
from ._noise import NoiseModel
from ._observation_noise import observation_noise
from ._prior import term_prior
from ._solve import compile_normal, compile_steps, default_solver, normal_at, solve
from ._uncertainty import covariance, effective_clusters, identifiability, robust_covariance

__all__ = [
    "BundleData",
    "BundleProblem",
    "CalibrationResult",
    "READABLE_VERSIONS",
    "SCHEMA_VERSION",
    "Frames",
    "align_to_gauge",
    "bundle_normal",
    "fit",
    "predict_residuals",
    "residuals",
    "robot_world_hand_eye",
    "score_effects",
]

ROBUST = ("huber", "cauchy")
#: parameter groups `fit` can hold at their start values
HOLDABLE = ("camera_from_base", "flange_from_tool", "constellation")
_ROBUST_K = {"huber": 2.0, "cauchy": 2.0}
_TANGENT = ("tx", "ty", "tz", "rx", "ry", "rz")
_OUTLIER_U = 4.0  # frames whose noise-normalised residual RMS exceeds this are outliers
#: [s] frames in motion form clusters of this span in the robust covariance (a static
#: dwell is one cluster): a model error is shared by neighbouring frames; longer for
#: long recordings, so that there are at most `MAX_CLUSTERS`
CLUSTER_SPAN = 0.25
MAX_CLUSTERS = 400
#: the cluster-robust covariance needs a `(P, P)` matrix per frame of a chunk and per
#: cluster: above this many global parameters (a joint angle error map has hundreds) it
#: is not computed and the Gauss–Newton (posterior) covariance is reported alone
ROBUST_MAX_GLOBAL = 400
#: σ above which a determined rigid-transform parameter is reported as weak: translation
#: [m] ("t…") and rotation [rad] ("r…", 0.1 mm at 1 m): a third of the tracker's noise
#: and what ISO 9283 accuracies of tenths of a millimetre can no longer ignore
WEAK_SIGMA = {"t": 20e-6, "r": 100e-6}


# ----------------------------------------------------------------------------- gauge


def align_to_gauge(
    result: CalibrationResult, constellation: np.ndarray, flange_from_tool: Pose, led_ids=None
) -> tuple[np.ndarray, Pose]:
    """Express another (constellation, flange←tool) pair — e.g. the simulation truth —
    in `result`'s tool-frame gauge, so that they can be compared entry by entry.

    Finds the tool-frame change G with ``G·p − p_ref`` free of rigid motion (to second
    order) and returns ``(G·p, flange_from_tool · G⁻¹)``; `led_ids` selects the rows of
    `constellation` (default: the result's LEDs in the same order).
    """
    p = np.asarray(constellation, float)
    if led_ids is not None:
        row = {int(i): k for k, i in enumerate(led_ids)}
        p = p[[row[int(i)] for i in result.led_ids]]
    if result.gauge == "probe":
        return p, flange_from_tool
    seen = ~np.isin(np.asarray(result.led_ids), np.asarray(result.unseen_leds, int))
    ref = np.asarray(result.gauge_reference)[seen]
    g = jaxlie.SE3.identity()
    for _ in range(3):
        pg = np.asarray(jax.vmap(g.apply)(jnp.asarray(p[seen])))
        a = cp.rigid_directions(pg)
        xi = np.linalg.lstsq(a, -(pg - ref).reshape(-1), rcond=None)[0]
        g = jaxlie.SE3.exp(jnp.asarray(xi)) @ g
    pg = np.asarray(jax.vmap(g.apply)(jnp.asarray(p)))
    fft = _se3(_wxyz_xyz(flange_from_tool)) @ g.inverse()
    return pg, _pose_of(fft.wxyz_xyz)


# ----------------------------------------------------------------------------- names


def _global_names(effects: Effects, free: tuple[str, ...]) -> list[str]:
    names = [f"camera_from_base.{t}" for t in _TANGENT]
    names += [f"flange_from_tool.{t}" for t in _TANGENT]
    for name in free:
        names += effect_component_names(name, np.shape(effects.get(name)))
    return names


# ----------------------------------------------------------------------------- fit


@dataclasses.dataclass(frozen=True)
class _Setup:
    """A recording prepared for the engine: the observations (`data`), the problem at its
    start (`bundle`), parameter names and which ones may be dropped, the normal matrix
    at the start (`h0`; `normal0` the engine's ``(H, b, cost)`` there), the clusters of
    the robust covariance and the noise model behind the weights."""

    data: CalibrationData
    bundle: BundleData
    gauge: str
    initial: dict
    free: tuple[str, ...]  # effects in the problem: estimated ones and held ones
    estimated: tuple[str, ...]
    in_model: np.ndarray  # θ entries of the poses, the estimated effects, the constellation
    q: int
    w_user: np.ndarray
    names_theta: list[str]
    phi_names: list[str]
    droppable: np.ndarray
    has_column: np.ndarray  # θ entries that are parameters (not padding of the basis)
    h0: np.ndarray
    n_residuals: int
    normal0: tuple | None
    clusters: tuple[np.ndarray, int]  # cluster of every chunked frame, their count
    clustered: bool  # the cluster-robust covariance is computed (`ROBUST_MAX_GLOBAL`)
    noise: NoiseModel | None  # the recording's noise model where it gave the weights
    noise_info: dict[str, Any]
    ahead: CompileAhead  # the fit's later kernels, compiling on a background thread


def _solve_pass(
    st: _Setup, bundle: BundleData, free_mask, solver, max_iter, say, label, start=None
):
    """One engine solve from `bundle`'s current values (`start`: the normal equations
    there, if known); returns the re-centred bundle."""
    say(label)
    sol = solve(
        bundle_normal,
        bundle,
        np.zeros(len(st.names_theta)),
        free_mask,
        n_residuals=st.n_residuals,
        solver=solver,
        max_steps=max_iter,
        start=start,
        size=len(st.names_theta),
    )
    problem = cp.recentre(bundle.problem, sol.theta, bundle.basis)
    return dataclasses.replace(bundle, problem=problem), sol


def fit(
    recording: Recording,
    *,
    estimate: Sequence[str] = (),
    robust: str | None = None,
    init: CalibrationResult | None = None,
    weights: np.ndarray | None = None,
    solver: Any = None,
    max_iter: int = 50,
    chunk: int | None = None,
    progress: Callable[[str], None] | None = None,
    suggest: int = 0,
    space: Sequence[str] = (),
    hold: Sequence[str] = (),
    robust_sigma: bool = True,
    motion_threshold: float | None = None,
) -> CalibrationResult:
    """Bundle-calibrate `recording` (see the module docstring).

    **Arguments:**

    - `estimate`: names of `Effects` fields to estimate besides the poses and the
      constellation (e.g. ``("time_offset", "joint_offset")``); the others stay at
      `init`'s values (zero by default).
    - `robust`: ``None``, ``"huber"`` or ``"cauchy"`` (IRLS).
    - `init`: start from this calibration instead of the closed-form initialisation
      (its poses, constellation and effects are the start; its gauge reference stays
      the gauge reference, so the result is in the same gauge; effects not in
      `estimate` stay at its values).
    - `weights`: `(N, M)` per-LED-observation weights ∝ 1/variance, aligned with the
      recording's frames and `led_ids`; default: a noise model estimated from the data.
    - `solver`: an Optimistix least-squares solver (default: Levenberg–Marquardt,
      `robtraj.estimate.default_solver`).
    - `progress`: called with a short status line at each stage.
    - `suggest`: when the recording leaves a rigid-transform parameter undetermined or
      weak (σ above `WEAK_SIGMA`), list this many static robot poses that would determine
      it best (`identifiability["next_poses"]`, `robtraj.estimate._next_poses`).
    - `space`: effects that enter the problem held at their start values besides the
      estimated ones. The estimate is the same; fits of one recording in one space share
      one compilation whatever they estimate (the discrepancy search fits in the whole
      library's space), at the price of Jacobian columns for the held effects.
    - `robust_sigma`: compute the cluster-robust covariance (one more pass over the
      recording, with per-cluster sums); False leaves the Gauss–Newton one in its place
      (fits whose σ are not reported, e.g. the discrepancy search's refits and held-out
      fits).
    - `hold`: parameter groups held at their start values (`init`'s): any of
      ``"camera_from_base"``, ``"flange_from_tool"``, ``"constellation"`` (to refit only
      the rigid transforms of another recording under a calibrated model).
    - `motion_threshold`: speed [rad/s] below which a joint counts as at rest for the
      dictionary's velocity-sign terms (default: `init`'s, else
      `robtraj.model.MOTION_THRESHOLD`); data, not a parameter: fits that differ only
      in it share one compilation.

    **Returns:** a `CalibrationResult` (`converged` False, with the reason in
    `convergence`, when a solve stopped before its criterion held). Raises `UserError`
    for unusable input.
    """
    say = progress or (lambda _msg: None)
    if robust is not None and robust not in ROBUST:
        raise UserError(f"unknown robust loss {robust!r} (choose from {', '.join(ROBUST)})")
    bad = [h for h in hold if h not in HOLDABLE]
    if bad:
        raise UserError(f"cannot hold {', '.join(bad)} (choose from {', '.join(HOLDABLE)})")
    method = type(solver).__name__ if solver else "Levenberg–Marquardt"
    solver = solver or default_solver()
    estimate = tuple(dict.fromkeys((*clock_effects(recording.robot), *estimate)))
    st = _setup(
        recording,
        estimate,
        init,
        weights,
        chunk,
        say,
        space=space,
        motion=motion_threshold,
        solver=solver,
        clustered=robust_sigma,
    )
    noise, noise_info = st.noise, st.noise_info
    robust_sigma = robust_sigma and st.clustered
    data, q, free, w_user = st.data, st.q, st.free, st.w_user
    held = np.array([n.split(".", 1)[0] in hold for n in st.names_theta])
    if not np.any(st.has_column & st.in_model & ~held):
        raise UserError("nothing to fit: every parameter of the problem is held")
    free_mask, ident = identifiability(
        st.h0, st.phi_names, st.has_column & st.in_model & ~held, st.droppable
    )
    if ident["dropped"]:
        say("not identifiable, fixed: " + ", ".join(d["parameter"] for d in ident["dropped"]))

    def residual_stats(b: BundleData):
        d, theta = cp.evaluate(jnp.zeros(q), b.problem.constellation, b.problem, b.chunks)
        d, theta = np.asarray(d)[: data.n_frames], np.asarray(theta)[: data.n_frames]
        return d, theta, np.einsum("fli,fli->fl", d, d)  # no (frames, leds, 3) temporary

    used = w_user > 0
    w = w_user
    label = {"user_weights": "fit", "uniform": "uniformly weighted fit"}.get(
        noise_info["kind"], "noise-weighted fit"
    )
    bundle, sol = _solve_pass(
        st, st.bundle, free_mask, solver, max_iter, say, f"{label}: {method}", st.normal0
    )
    sols = [sol]
    w_noise = w
    if robust is not None:
        for it in range(5):
            _, _, sq = residual_stats(bundle)
            dof = max(1, 3 * int(used.sum()) - int(free_mask.sum()))
            s2 = float(np.sum(w * sq) / dof)
            u = np.sqrt(w_noise * sq / 3.0 / max(s2, 1e-300))
            k = _ROBUST_K[robust]
            rho = (
                np.minimum(1.0, k / np.maximum(u, 1e-12))
                if robust == "huber"
                else 1 / (1 + (u / k) ** 2)
            )
            w = np.where(used, w_noise * rho, 0.0)
            del sq, u, rho
            bundle = dataclasses.replace(bundle, chunks=cp.with_weights(bundle.chunks, w))
            bundle, sol = _solve_pass(
                st,
                bundle,
                free_mask,
                solver,
                max_iter,
                say,
                f"robust ({robust}) pass {it + 1}: {method}",
            )
            sols.append(sol)
            if sol.steps <= 2:
                break

    say("covariance and residual statistics")
    st.ahead.wait()
    # the normal equations at the estimate (per cluster for the robust covariance) on a
    # background thread, while the residuals are summarised here
    p_theta = jnp.zeros(len(st.names_theta))
    cluster, n_clusters = st.clusters
    if robust_sigma:
        padded = _padded_clusters(n_clusters)
        final = in_background(bundle_normal_clustered, p_theta, bundle, cluster, padded)
    else:
        final = in_background(normal_at, bundle_normal, p_theta, bundle)
    d, theta, sq = residual_stats(bundle)
    seen_angle = float(np.quantile(theta[used], 0.99)) if data.has_normals else np.pi
    del theta
    frames_rec = data.n_recording_frames
    full_res = np.full((frames_rec, data.n_leds, 3), np.nan)
    full_res[data.frame] = d
    del d
    unused_frame, unused_led = np.nonzero(~used)
    full_res[data.frame[unused_frame], unused_led] = np.nan
    if robust_sigma:
        h, _, chi2, cluster_h, scores = (np.asarray(x) for x in final.result())
        keep = np.r_[np.arange(n_clusters), np.arange(padded, cluster_h.shape[0])]
        cluster_h, scores = cluster_h[keep], scores[keep]
    else:
        h, _, chi2 = (np.asarray(x) for x in final.result())
    # χ² of the observations: the normal equations' cost holds the terms' prior too
    chi2 = float(chi2) - float(bundle.prior.cost(cp.prior_values(jnp.zeros(q), bundle)))
    n_res = 3 * int(used.sum()) + (6 * int(bundle.probe.probed.shape[0]) if bundle.probe else 0)
    cov_unit, rank = covariance(h, free_mask)
    s2 = chi2 / max(1, n_res - rank)
    basis = np.asarray(bundle.basis)
    t = np.zeros((q + 3 * data.n_leds, q + basis.shape[1]))
    t[:q, :q] = np.eye(q)
    t[q:, q:] = basis
    cov_phi = t @ (s2 * cov_unit) @ t.T
    if robust_sigma:
        cov_robust = t @ robust_covariance(h, free_mask, cluster_h, scores) @ t.T
        g_eff = effective_clusters(h, free_mask, cluster_h, t)
        del cluster_h, scores
    else:
        cov_robust, g_eff = cov_phi, np.full(t.shape[0], np.nan)
    phi_names = st.names_theta[:q] + [
        f"constellation[LED {int(i)}].{c}" for i in data.led_ids for c in ("x", "y", "z")
    ]
    n_led = 3 * int(used.sum())
    logw = float(np.sum(np.log(w[used]))) * 3.0
    loglik = -0.5 * n_led * (math.log(2 * math.pi * chi2 / n_led) + 1.0) + 0.5 * logw

    per_frame = np.full(frames_rec, np.nan)
    cnt = used.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame[data.frame] = np.where(cnt > 0, np.sqrt(np.sum(sq * used, 1) / cnt), np.nan)
        per_led = np.sqrt(np.sum(sq * used, 0) / used.sum(0))
        u_frame = np.sqrt(np.sum(w_noise * sq * used, 1) / np.maximum(3 * cnt, 1) / s2)
    outliers = data.frame[(cnt > 0) & (u_frame > _OUTLIER_U)]
    # weights in the recording's LED columns, so that they can be passed back as `weights=`
    rec_col = {int(i): k for k, i in enumerate(recording.led_ids)}
    full_w = np.zeros((frames_rec, recording.n_leds))
    full_w[np.ix_(data.frame, [rec_col[int(i)] for i in data.led_ids])] = w

    problem = bundle.problem
    eff = problem.effects
    effects_out = {n: np.asarray(eff.get(n)).tolist() for n in free}
    effects_out.update({k: v for k, v in eff.to_dict().items() if k not in effects_out})
    ident = {
        **ident,
        "fixed_parameters": [phi_names[i] for i in range(q) if st.in_model[i] and not free_mask[i]],
    }
    sig = np.sqrt(np.clip(np.maximum(np.diag(cov_phi), np.diag(cov_robust)), 0, None))
    ident["weak"] = _weak(phi_names[:12], sig[:12], set(ident["undetermined"]))
    # poses are suggested for the global parameters (rigid transforms, effects); an
    # undetermined LED coordinate needs that LED seen, not another pose
    watched = list(
        dict.fromkeys(
            [w["parameter"] for w in ident["weak"]]
            + [u for u in ident["undetermined"] if u in st.names_theta[:q]]
        )
    )
    if watched and suggest:
        say("poses that would determine " + ", ".join(watched))
        nxt = _next_poses(
            recording,
            data,
            bundle,
            h,
            free_mask,
            s2,
            st.names_theta,
            watched,
            noise,
            seen_angle,
            w_noise,
            suggest,
        )
        ident["next_poses"] = None if nxt is None else nxt.to_json()
    converged = all(x.converged for x in sols)
    failed = [x for x in sols if not x.converged]
    model = np.flatnonzero(np.r_[st.in_model[:q], np.ones(len(phi_names) - q, bool)])
    return CalibrationResult(
        robot=recording.robot.model_document(),
        camera_from_base=_pose_of(problem.camera_from_base),
        flange_from_tool=_pose_of(problem.flange_from_tool),
        led_ids=np.asarray(data.led_ids),
        constellation=np.asarray(problem.constellation),
        effects=effects_out,
        estimated=st.estimated,
        parameter_names=tuple(phi_names[i] for i in model),
        covariance=cov_phi[np.ix_(model, model)],
        covariance_robust=cov_robust[np.ix_(model, model)],
        clusters_effective=g_eff[model],
        n_clusters=int(n_clusters + (bundle.probe.probed.shape[0] if bundle.probe else 0)),
        residual_rms_m=float(np.sqrt(np.mean(sq[used]))),
        noise_sigma_m=float(np.sqrt(np.mean(sq[used]) / 3.0)),
        gauge=st.gauge,
        gauge_reference=np.asarray(data.reference),
        motion_threshold=data.motion_threshold,
        identifiability=ident,
        iterations=sum(x.steps for x in sols),
        converged=converged,
        convergence=sols[-1].reason if converged else failed[0].reason,
        chi2=chi2,
        n_residuals=n_res,
        n_params=rank,
        log_likelihood=loglik,
        residual_rms_per_led={
            int(i): float(v) for i, v in zip(data.led_ids, per_led) if np.isfinite(v)
        },
        residual_rms_per_frame=per_frame,
        residuals=full_res,
        weights=full_w,
        outlier_frames=outliers,
        noise_model=noise_info,
        initial=st.initial,
        unseen_leds=data.unseen_leds,
        robust=robust,
    )


def predict_residuals(
    recording: Recording, calibration: CalibrationResult, space: Sequence[str] = ()
) -> np.ndarray:
    """Residuals (measured − predicted) [m], camera frame, of every seen observation of
    `recording` under `calibration`'s parameters, none refitted: `(frames, leds, 3)` in
    the recording's frames and `calibration.led_ids` order, NaN where unseen (as
    `CalibrationResult.residuals`, which leaves out observations of weight zero).
    `space`: that of the fit which made `calibration` (`fit`), whose compiled kernels
    then serve again.

    Serves held-out evaluation: fit with weights zero on some frames, then compare the
    prediction there."""
    space = tuple(dict.fromkeys((*calibration.estimated, *space)))
    st = _setup(recording, (), calibration, None, None, lambda _m: None, False, space)
    data = st.data
    d, _ = cp.evaluate(
        jnp.zeros(st.q), st.bundle.problem.constellation, st.bundle.problem, st.bundle.chunks
    )
    d = np.asarray(d)[: data.n_frames]
    out = np.full((data.n_recording_frames, data.n_leds, 3), np.nan)
    out[data.frame] = np.where(data.seen[..., None], d, np.nan)
    col = {int(i): k for k, i in enumerate(data.led_ids)}
    keep = [col.get(int(i)) for i in calibration.led_ids]
    return np.stack(
        [out[:, k] if k is not None else np.full(out.shape[::2], np.nan) for k in keep], 1
    )


def _weak(names, sigma, undetermined) -> list[dict[str, Any]]:
    """Rigid-transform parameters determined, but with σ above `WEAK_SIGMA`."""
    out = []
    for name, s in zip(names, sigma):
        tol = WEAK_SIGMA[name.rsplit(".", 1)[1][0]]
        if name not in undetermined and s > tol:
            out.append({"parameter": name, "sigma": float(s), "tolerance": tol})
    return out


def _next_poses(recording, data, bundle, h, free, s2, names, watched, noise, seen_angle, w, n):
    """`next_poses` for this calibration: the recording's noise model (or one variance
    from the weights), the joint log, the frame rate and the distances seen."""
    pos = np.asarray(recording.positions)
    dist = np.linalg.norm(pos[np.isfinite(pos[..., 0])], axis=-1)
    lo, hi = np.quantile(dist, [0.01, 0.99])
    if noise is not None:
        row = {int(i): k for k, i in enumerate(noise.led_ids)}
        level = np.array([row.get(int(i), 0) for i in data.led_ids])

        def variance_at(theta, r, led):
            return noise.variance_at(theta, r, level[led])
    else:
        v = float(1.0 / np.mean(w[w > 0]))

        def variance_at(theta, r, led):
            return np.full(np.shape(theta), v)

    rate = 1.0 / float(np.median(np.diff(data.time))) if data.n_frames > 1 else 1.0
    return next_poses(
        bundle, h, free, s2, names, watched, variance_at, data.joints, rate,
        seen_angle, (0.95 * lo, 1.05 * hi), data.led_seen, n,
    )  # fmt: skip


def _clusters(data: CalibrationData, chunks: Frames) -> tuple[np.ndarray, int]:
    """Cluster index of every chunked frame `(chunks, chunk)` for the robust covariance,
    and the cluster count: each static dwell of the robot is one cluster, the frames
    between dwells form clusters of `CLUSTER_SPAN` seconds or more (padding frames: cluster 0,
    they carry no weight)."""
    span = max(CLUSTER_SPAN, float(data.time[-1] - data.time[0]) / (MAX_CLUSTERS - 1))
    label = np.floor((data.time - data.time[0]) / span).astype(np.int64)
    for k, frames in enumerate(dwells(data, 0.2)):
        label[frames] = -1 - k
    _, ids = np.unique(label, return_inverse=True)
    k, size = chunks.time.shape[:2]
    out = np.zeros(k * size, np.int64)
    out[: ids.size] = ids
    return out.reshape(k, size), int(ids.max()) + 1


def _padded_clusters(n_clusters: int) -> int:
    """The cluster count as a static shape of the clustered kernel: padded so that
    recordings of one shape share a compilation (the empty clusters are cut before the
    jackknife)."""
    return -(-n_clusters // 64) * 64


def _normal_at_zero(bundle: BundleData, p: int):
    return normal_at(bundle_normal, jnp.zeros(p), bundle)


def score_effects(
    recording: Recording,
    current: CalibrationResult,
    candidates: Sequence[str],
    *,
    weights: np.ndarray | None = None,
    chunk: int | None = None,
) -> dict[str, dict[str, Any]]:
    """Rao's score (Lagrange-multiplier) test of adding each candidate effect to `current`.

    The normal equations ``H = JᵀWJ``, ``b = JᵀWr`` are accumulated once at `current`'s
    estimate with every effect of the library free. For a candidate with entries C added
    to `current`'s free parameters P (poses, constellation, estimated effects), F = P ∪ C,
    the statistic is the Gauss–Newton predicted decrease of χ²,
    ``bᵀ H⁺_FF b − bᵀ H⁺_PP b``: the likelihood ratio of a model linear in the new
    entries, χ²(k) under the null with k the rank gained. Entries of C that lie in null
    directions of ``H_FF`` (not identifiable next to P, e.g. joint 1's offset against the
    camera's yaw) are left out of k and listed in ``fixed``.

    One pass over the recording serves every candidate, and since the problem always has
    all effects free it compiles once per recording shape — where refitting costs a
    compilation and a solve per candidate.

    **Arguments:** `weights` as in `fit` (default: `current.weights`).

    **Returns:** ``{effect: {"statistic", "dof", "parameters", "fixed"}}`` (χ² units).
    """
    _check_names(candidates)
    w = current.weights if weights is None else weights
    space = library_space(candidates, current.estimated, tuple(current.effects))
    st = _setup(recording, space, current, w, chunk, lambda _m: None, start_only=True)
    H = st.h0
    b = np.asarray(st.normal0[1])
    fixed_now = set(current.identifiability.get("fixed_parameters", []))
    names = st.names_theta
    mine = set(current.estimated)

    def entries(effect):
        return [i for i, n in enumerate(names[12 : st.q], 12) if _effect_of(n) == effect]

    base = np.zeros(len(names), bool)
    base[:12] = True
    base[st.q :] = st.has_column[st.q :]
    for e in mine:
        for i in entries(e):
            base[i] = names[i] not in fixed_now
    inv_p, rank_p = covariance(H, base)
    stat_p = float(b @ inv_p @ b)
    out = {}
    for effect in dict.fromkeys(candidates):
        cols = [i for i in entries(effect) if not base[i]]
        free = base.copy()
        free[cols] = True
        droppable = np.zeros(len(names), bool)
        droppable[cols] = True
        free, ident = identifiability(H, st.phi_names, free, droppable)
        inv_f, rank_f = covariance(H, free)
        out[effect] = {
            "statistic": max(0.0, float(b @ inv_f @ b) - stat_p),
            "dof": int(rank_f - rank_p),
            "parameters": [names[i] for i in cols if free[i]],
            "fixed": [d["parameter"] for d in ident["dropped"]],
        }
    return out


def library_space(*extra: Sequence[str]) -> tuple[str, ...]:
    """The library (`robtraj.model.LIBRARY`) and the effects named in `extra`, in
    `EFFECT_NAMES` order: the problem space of the discrepancy search, shared by its
    fits, score tests and held-out predictions so that they compile once."""
    wanted = set(LIBRARY).union(*map(set, extra))
    return tuple(n for n in known_effects() if n in wanted)


def _check_names(names) -> None:
    known = known_effects()
    bad = [e for e in names if e not in known]
    if bad:
        raise UserError(
            f"unknown effect(s) {', '.join(bad)} (known: the library "
            f"{', '.join(LIBRARY)}, link_twist and the dictionary's terms)"
        )


def _structure(
    ahead: CompileAhead,
    data: CalibrationData,
    effects0: Effects,
    names: tuple[tuple[str, ...], tuple[str, ...], bool],
    sizes: tuple[int, int],
    start: np.ndarray,
    probe_poses: tuple,
    chunk: int | None,
    solver,
    normal: bool,
    clustered: bool,
):
    """The bundle problem of `_setup` at placeholder poses and uniform weights (its
    shapes and static parts are those of the fit; `probe_poses`: the recording's
    `/probe` and the clock offset), the clusters of the robust covariance and the
    compilations of the fit's kernels (queued on `ahead`, after this): returns
    ``(bundle, clusters, futures of the kernels the start and the solve need)``."""
    free, estimated, start_only = names
    q, p = sizes  # global parameters, all of θ
    probe = cp.probe_observations(probe_poses[0], data, probe_poses[1])
    basis = cp.gauge_basis(data.reference, data.led_seen, probe is not None)
    kinematic = any(cp.is_kinematic(n) for n in free) or any(
        cp.is_kinematic(n) for n in effects0.terms
    )
    identity = jax.device_put(np.array([1.0, 0, 0, 0, 0, 0, 0]))
    problem = BundleProblem(
        robot=data.robot,
        camera_from_base=identity,
        flange_from_tool=identity,
        constellation=jax.device_put(np.asarray(start, float)),
        normals=jax.device_put(data.normals),
        effects=effects0,
        log_time=jax.device_put(data.log_time),
        joints=jax.device_put(data.joints),
        free=free,
        kinematic=kinematic,
        # LED-level effects at zero move no LED: the rigid path serves while none is
        # estimated (a step would move them), or for the normal equations at the start
        rigid_leds=(start_only or not any(cp.is_led_level(n) for n in estimated))
        and all(
            float(np.max(np.abs(effects0.get(n)))) == 0.0
            for n in (*cp.LED_EFFECTS, *effects0.terms)
            if cp.is_led_level(n)
        ),
        led_columns=start_only,
    )
    chunks = cp.chunked_frames(data, data.seen.astype(float), cp.chunk_size(data.n_frames, chunk))
    if not kinematic:
        fl = cp.fixed_flange_poses(data.robot, effects0, problem.log_time, problem.joints, chunks)
        chunks = dataclasses.replace(chunks, base_from_flange=fl)
    clusters = _clusters(data, chunks)
    blocks, at = [], 12
    for name in free:
        if name in estimated:
            blocks.append((name, at))
        at += int(np.size(effects0.get(name)))
    bundle = BundleData(
        problem=problem,
        chunks=chunks,
        basis=jax.device_put(basis),
        probe=probe,
        prior=term_prior(blocks),
    )
    first = []
    if normal:
        theta0 = jnp.zeros(p)
        first.append(compile_normal(ahead, bundle_normal, theta0, bundle))
    if solver is not None:
        first.append(compile_steps(ahead, solver, p))
        ahead.submit(cp.evaluate, jnp.zeros(q), problem.constellation, problem, chunks)
        if clustered:
            padded = _padded_clusters(clusters[1])
            ahead.submit(bundle_normal_clustered, theta0, bundle, clusters[0], padded)
    return bundle, clusters, first


def _setup(
    recording,
    estimate,
    init,
    weights,
    chunk,
    say,
    normal=True,
    space=(),
    motion=None,
    start_only=False,
    solver=None,
    clustered=False,
) -> _Setup:
    """Observations, weights, closed-form start and problem of one fit. `weights` None:
    from the recording's noise model (uniform where it cannot be estimated) with
    `normal`, else uniform. `start_only`: the normal equations are wanted at the start
    alone (no step is taken): LED-level effects at zero then take the rigid path even
    when free. With `normal`, the kernels of the fit (its normal equations; the steps of
    `solver`; the clustered pass with `clustered`) are compiled on a background thread
    while the weights and the start are computed (`_compile_ahead`)."""
    estimate = tuple(dict.fromkeys(estimate))
    _check_names((*estimate, *space))
    order = known_effects()
    free = tuple(n for n in order if n in estimate or n in space)
    estimated = tuple(n for n in order if n in estimate)
    dictionary_terms = tuple(n for n in free if n not in EFFECT_NAMES)

    # observations
    reference = start = None
    if init is not None and recording.tool is not None:
        reference = _per_tool_led(recording, init.led_ids, init.gauge_reference)
        start = _per_tool_led(recording, init.led_ids, init.constellation)
    tau0 = 0.0 if init is None else init.time_offset
    if motion is None:
        motion = MOTION_THRESHOLD if init is None else init.motion_threshold
    if not (np.isfinite(motion) and motion > 0):
        raise UserError(f"the motion threshold must be a positive speed [rad/s], not {motion}")
    checked = check(recording, time_offset=tau0, constellation=reference)
    noise_job = None
    if weights is None and normal:
        say("noise model of the recording")
        noise_job = in_background(observation_noise, recording)
    data = prepare(
        recording,
        time_offset=tau0,
        constellation=reference,
        motion_threshold=float(motion),
        checked=checked,
    )
    if start is not None:
        col = {int(i): k for k, i in enumerate(recording.tool.led_ids)}
        start = start[[col[int(i)] for i in data.led_ids]]
    else:
        start = data.reference
    init_terms = [n for n in (init.effects if init is not None else ()) if n not in EFFECT_NAMES]
    effects0 = Effects.zeros(
        data.robot.n_joints, tuple(dict.fromkeys((*dictionary_terms, *init_terms)))
    )
    if init is not None:
        for k, v in init.effects.items():
            effects0 = effects0.with_value(k, v)

    # the problem's structure and its kernels, on the compiling thread meanwhile (the
    # constellation basis has 3 columns per LED, padded: fixed shapes)
    gnames = _global_names(effects0, free)
    q = len(gnames)
    names_theta = gnames + [f"constellation.c{j}" for j in range(3 * data.n_leds)]
    if clustered and q > ROBUST_MAX_GLOBAL:
        say(f"{q} global parameters: Gauss–Newton covariance only (no cluster-robust σ)")
        clustered = False
    ahead = CompileAhead()
    structure = ahead.run(
        _structure,
        ahead,
        data,
        effects0,
        (free, estimated, start_only),
        (q, len(names_theta)),
        start,
        (recording.probe, tau0),
        chunk,
        solver if normal else None,
        normal,
        clustered,
    )

    # closed-form start (while the noise model is estimated)
    say(f"{data.n_frames} frames, {data.n_leds} LEDs: closed-form initialisation")
    if init is None:
        cft, bff, _ = pose_pairs(data, effects0, data.reference)
        z, x = closed_form_start(cft, bff, data.nominal_flange_from_tool)
    else:
        z, x = _wxyz_xyz(init.camera_from_base), _wxyz_xyz(init.flange_from_tool)
    initial = {"camera_from_base": _pose_of(z), "flange_from_tool": _pose_of(x)}

    # weights
    noise, noise_info = None, {"kind": "user_weights"}
    if noise_job is not None:
        try:
            noise, var = noise_job.result()
        except UserError as err:
            noise_info = {"kind": "uniform", "reason": str(err)}
        else:
            weights, noise_info = np.where(np.isfinite(var), 1.0 / var, 0.0), noise.to_dict()
            del var
    if weights is not None:
        w_user = _user_weights(recording, data, weights)
    else:
        w_user = data.seen.astype(float)

    # problem
    bundle, clusters, first = structure.result()
    probe, basis = bundle.probe, np.asarray(bundle.basis)
    gauge = "probe" if probe is not None else "reference_constellation"
    # the observations live on in the chunks; the frame-major copy is not needed again
    data = dataclasses.replace(data, measured=np.zeros((0, data.n_leds, 3)))
    bundle = eqx.tree_at(
        lambda b: (b.problem.camera_from_base, b.problem.flange_from_tool, b.chunks),
        bundle,
        (jax.device_put(z), jax.device_put(x), cp.with_weights(bundle.chunks, w_user)),
    )
    ahead.wait(*first)

    held = set(free) - set(estimated)
    redundant = set(redundant_link_parameters(data.robot))
    in_model = np.array([_effect_of(n) not in held and n not in redundant for n in names_theta])
    has_column = np.concatenate([np.ones(q, bool), np.any(basis != 0, axis=0)])
    n_res = 3 * int(np.sum(w_user > 0)) + (0 if probe is None else 6 * probe.probed.shape[0])
    normal0 = _normal_at_zero(bundle, len(names_theta)) if normal else None
    h0 = np.asarray(normal0[0]) if normal else np.zeros((0, 0))
    if not np.all(np.isfinite(h0)):
        raise UserError("the observations give non-finite normal equations at the start")
    return _Setup(
        data=data,
        bundle=bundle,
        gauge=gauge,
        initial=initial,
        free=free,
        estimated=estimated,
        in_model=in_model,
        q=q,
        w_user=w_user,
        names_theta=names_theta,
        phi_names=_phi_names_for(names_theta, q, basis, data),
        droppable=np.array([12 <= i < q for i in range(len(names_theta))]),
        has_column=has_column,
        n_residuals=n_res,
        h0=h0,
        normal0=normal0,
        clusters=clusters,
        clustered=clustered,
        noise=noise,
        noise_info=noise_info,
        ahead=ahead,
    )


def _effect_of(parameter: str) -> str:
    """The effect a parameter name belongs to: ``link_length[1].a`` → ``link_length``,
    ``joint1_harmonic2.sin`` → ``joint1_harmonic2``."""
    return parameter.partition("[")[0].partition(".")[0]


def _phi_names_for(names_theta, q, basis, data) -> list[str]:
    """Readable names for θ: constellation coefficients named by their dominant LED."""
    out = list(names_theta[:q])
    for j in range(basis.shape[1]):
        k = int(np.argmax(np.abs(basis[:, j])))
        out.append(f"constellation[LED {int(data.led_ids[k // 3])}].{'xyz'[k % 3]}")
    return out


def _per_tool_led(rec: Recording, ids, values) -> np.ndarray:
    """`values` (rows per `ids`) as rows per tool LED; the nominal where `ids` lacks one."""
    row = {int(i): k for k, i in enumerate(ids)}
    vals = np.asarray(values, float)
    return np.array(
        [
            vals[row[int(i)]] if int(i) in row else rec.tool.constellation[k]
            for k, i in enumerate(rec.tool.led_ids)
        ]
    )


def _user_weights(rec: Recording, data: CalibrationData, weights: np.ndarray) -> np.ndarray:
    w = np.asarray(weights, float)
    if w.shape != (rec.n_frames, rec.n_leds):
        raise UserError(f"weights have shape {w.shape}, expected {(rec.n_frames, rec.n_leds)}")
    col = {int(i): k for k, i in enumerate(rec.led_ids)}
    w = w[data.frame][:, [col[int(i)] for i in data.led_ids]]
    w = np.where(data.seen & np.isfinite(w) & (w > 0), w, 0.0)
    if not np.any(w > 0):
        raise UserError("all weights are zero")
    return w
