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
- **Solver**: Levenberg–Marquardt over normal equations accumulated in chunks of
  frames (bounded memory, no Jacobian of the whole recording), lineax Cholesky for
  each damped step (`_calib_lm`). `solver="optimistix"` instead runs
  `optimistix.LevenbergMarquardt` on the pure `residuals` of all frames at once (small
  recordings; same optimum).
- **Initialisation** in closed form (`_calib_init`): weighted Procrustes tool poses on
  static dwells + Shah's robot-world/hand-eye solution.
- **Noise model**: by default the per-LED noise variance is estimated from the
  residuals as a function of the LED's emission angle (quantile bins, linear
  interpolation) and the fit repeated with inverse-variance weights, so that the
  covariance ``σ̂² (JᵀWJ)⁻¹`` (``σ̂² = χ²/(n − p)``) is honest for heteroscedastic data.
- **Robust losses** (`robust="huber"|"cauchy"`): IRLS weights on the per-LED
  noise-normalised residual; frames whose residuals stand out are reported.
- **Identifiability**: null directions of the column-scaled normal matrix are named;
  confounded effect parameters are fixed at their initial values and reported.
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
from ..model import EFFECT_NAMES, Effects
from ..recording import Pose, Recording
from . import _calib_lm as lm, _calib_problem as cp
from ._calib_data import CalibrationData, prepare
from ._calib_init import pose_pairs, robot_world_hand_eye
from ._calib_problem import BundleParams, BundleProblem, Frames, residual_fn, residuals
from ._calib_result import CalibrationResult, _pose_of, _se3, _wxyz_xyz

__all__ = [
    "BundleParams",
    "BundleProblem",
    "CalibrationResult",
    "Frames",
    "align_to_gauge",
    "fit",
    "residual_fn",
    "residuals",
    "robot_world_hand_eye",
    "score_effects",
]

ROBUST = ("huber", "cauchy")
_ROBUST_K = {"huber": 2.0, "cauchy": 2.0}
_TANGENT = ("tx", "ty", "tz", "rx", "ry", "rz")
_OUTLIER_U = 4.0  # frames whose noise-normalised residual RMS exceeds this are outliers
_PROBE_SIGMA = (20e-6, 2e-4)  # [m], [rad] assumed probe uncertainty


# ----------------------------------------------------------------------------- gauge


def _rigid_directions(reference: np.ndarray) -> np.ndarray:
    """`(3m, 6)`: LED displacements of a small rigid motion ``[t, ω]`` (``t + ω × p``)."""
    m = reference.shape[0]
    a = np.zeros((m, 3, 6))
    a[:, :, :3] = np.eye(3)
    px, py, pz = reference.T
    z = np.zeros(m)
    # ω × p = −[p]× ω
    a[:, :, 3:] = -np.stack(
        [np.stack([z, -pz, py], -1), np.stack([pz, z, -px], -1), np.stack([-py, px, z], -1)], 1
    )
    return a.reshape(3 * m, 6)


def _gauge_basis(reference: np.ndarray) -> np.ndarray:
    """Orthonormal basis `(3m, 3m − 6)` of constellation corrections free of rigid motion."""
    u, _, _ = np.linalg.svd(_rigid_directions(reference), full_matrices=True)
    return u[:, 6:]


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
        a = _rigid_directions(pg)
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
        shape = np.shape(getattr(effects, name))
        if shape == ():
            names.append(name)
        elif name == "link_length":
            names += [f"link_length[{j}].{c}" for j in range(shape[0]) for c in ("d", "a")]
        else:
            names += [f"{name}[{j}]" for j in range(int(np.prod(shape)))]
    return names


# ----------------------------------------------------------------------------- chunks


def _chunk_size(n: int, chunk: int | None) -> int:
    if chunk is not None:
        return int(chunk)
    return 256 if n <= 4096 else 1024 if n <= 65536 else 2048


def _chunks(data: CalibrationData, sqrt_w: np.ndarray, size: int) -> Frames:
    n = data.n_frames
    k = -(-n // size)
    pad = k * size - n

    def padded(a, fill_last=True):
        a = np.asarray(a)
        if pad:
            tail = np.repeat(a[-1:], pad, axis=0) if fill_last else np.zeros((pad, *a.shape[1:]))
            a = np.concatenate([a, tail])
        return jnp.asarray(a.reshape(k, size, *a.shape[1:]))

    return Frames(
        time=padded(data.time),
        direction=padded(data.direction),
        drift=padded(data.drift),
        measured=padded(data.measured),
        sqrt_weight=padded(sqrt_w, fill_last=False),
        base_from_flange=jnp.zeros((k, size, 7)),
    )


def _with_weights(chunks: Frames, w: np.ndarray) -> Frames:
    k, size = chunks.time.shape[:2]
    s = np.zeros((k * size, w.shape[1]))
    s[: w.shape[0]] = np.sqrt(w)
    return eqx.tree_at(lambda f: f.sqrt_weight, chunks, jnp.asarray(s.reshape(k, size, -1)))


# ----------------------------------------------------------------------------- probe


def _probe_frames(rec: Recording, data: CalibrationData, tau: float):
    if rec.probe is None or rec.probe.time.shape[0] == 0:
        return None
    t = np.asarray(rec.probe.time, float)
    inside = (t + tau >= data.log_time[0]) & (t + tau <= data.log_time[-1])
    if not inside.any():
        return None
    t = t[inside]
    from ..model import motion_direction

    drift = np.interp(t, data.time, data.drift)
    frames = Frames(
        time=jnp.asarray(t),
        direction=jnp.asarray(motion_direction(data.log_time, data.joints, t + tau)),
        drift=jnp.asarray(drift),
        measured=jnp.zeros((t.size, 0, 3)),
        sqrt_weight=jnp.zeros((t.size, 0)),
        base_from_flange=jnp.zeros((t.size, 7)),
    )
    probed = np.concatenate(
        [rec.probe.tool_pose.quaternion_wxyz[inside], rec.probe.tool_pose.position[inside]], -1
    )
    return frames, jnp.asarray(probed)


@eqx.filter_jit
def _probe_terms(g, problem: BundleProblem, frames: Frames, probed):
    """Probe-pose residuals ``−W·log(probed⁻¹ · predicted)`` linearised in g (`problem`
    must be `kinematic`: the probe times are not tracker frames)."""
    w = jnp.concatenate([jnp.full(3, 1 / _PROBE_SIGMA[0]), jnp.full(3, 1 / _PROBE_SIGMA[1])])

    def f(gg):
        tool, _ = cp.tool_poses(gg, problem, frames)
        err = jax.vmap(lambda a, b: (jaxlie.SE3(a).inverse() @ jaxlie.SE3(b)).log())(
            probed, tool.wxyz_xyz
        )
        return (w * err).reshape(-1)

    r = -f(g)
    j = jax.jacfwd(f)(g)
    return j.T @ j, j.T @ r, jnp.sum(r * r)


# ----------------------------------------------------------------------------- fit


def _noise_model(sq: np.ndarray, theta: np.ndarray, used: np.ndarray, by_angle: bool):
    """Per-observation variance [m²] per coordinate from the residuals (binned by angle)."""
    s2 = sq[used] / 3.0
    if not by_angle or s2.size < 200:
        v = float(np.mean(s2))
        return np.full(sq.shape, v), {"kind": "constant", "sigma_m": [math.sqrt(v)]}
    th = theta[used]
    edges = np.quantile(th, np.linspace(0, 1, 11))
    which = np.clip(np.searchsorted(edges, th, side="right") - 1, 0, 9)
    centre = np.array([th[which == b].mean() for b in range(10) if np.any(which == b)])
    var = np.array([s2[which == b].mean() for b in range(10) if np.any(which == b)])
    var = np.maximum(var, 1e-3 * var.max())
    out = np.interp(theta, centre, var)
    return out, {
        "kind": "emission_angle",
        "emission_angle_deg": np.rad2deg(centre).tolist(),
        "sigma_m": np.sqrt(var).tolist(),
    }


def fit(
    recording: Recording,
    *,
    estimate: Sequence[str] = (),
    robust: str | None = None,
    init: CalibrationResult | None = None,
    weights: np.ndarray | None = None,
    solver: str = "chunked",
    max_iter: int = 50,
    chunk: int | None = None,
    progress: Callable[[str], None] | None = None,
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
    - `solver`: ``"chunked"`` (normal equations in chunks, any length) or
      ``"optimistix"`` (`optx.LevenbergMarquardt` on all residuals; small recordings).
    - `progress`: called with a short status line at each stage.

    **Returns:** a `CalibrationResult`. Raises `UserError` for unusable input.
    """
    say = progress or (lambda _msg: None)
    if robust is not None and robust not in ROBUST:
        raise UserError(f"unknown robust loss {robust!r} (choose from {', '.join(ROBUST)})")
    if solver not in ("chunked", "optimistix"):
        raise UserError(f"unknown solver {solver!r}")
    st = _setup(recording, estimate, init, weights, chunk, say)
    data, problem, basis, probe, state = st.data, st.problem, st.basis, st.probe, st.state
    normal_fn, cost_fn, probe_extra, g0, q = st.normal_fn, st.cost_fn, st.probe_extra, st.g0, st.q
    free, gnames, w_user, gauge, initial = st.free, st.gnames, st.w_user, st.gauge, st.initial
    free_mask, ident = lm.identifiability(
        st.normal0.H, st.phi_names, np.ones(len(st.names_theta), bool), st.droppable
    )
    if ident["dropped"]:
        say("not identifiable, fixed: " + ", ".join(d["parameter"] for d in ident["dropped"]))

    def run_lm(pr, label):
        say(f"{label}: Levenberg–Marquardt")
        if solver == "optimistix":
            return _optimistix(pr, state["chunks"], free_mask, q, basis, normal_fn, max_iter)
        return lm.levenberg_marquardt(normal_fn, cost_fn, pr, free_mask, q, max_iter=max_iter)

    problem, normal, iters, converged = run_lm(problem, "unweighted fit")
    total_iters = iters

    def residual_stats(pr):
        d, theta = cp.evaluate(g0, pr.constellation, _jit_view(pr), state["chunks"])
        d, theta = np.asarray(d)[: data.n_frames], np.asarray(theta)[: data.n_frames]
        return d, theta, np.sum(d * d, -1)

    used = w_user > 0
    noise_info: dict[str, Any] = {"kind": "user_weights"}
    w = w_user
    if weights is None:
        d, theta, sq = residual_stats(problem)
        var, noise_info = _noise_model(sq, theta, used, data.has_normals)
        w = np.where(used, 1.0 / var, 0.0)
        state["chunks"] = _with_weights(state["chunks"], w)
        problem, normal, iters, converged = run_lm(problem, "noise-weighted fit")
        total_iters += iters
    w_noise = w
    if robust is not None:
        for it in range(5):
            d, theta, sq = residual_stats(problem)
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
            state["chunks"] = _with_weights(state["chunks"], w)
            problem, normal, iters, converged = run_lm(problem, f"robust ({robust}) pass {it + 1}")
            total_iters += iters
            if iters <= 2:
                break

    say("covariance and residual statistics")
    d, theta, sq = residual_stats(problem)
    n_res = 3 * int(used.sum())
    cov_theta, rank = lm.pinv_scaled(normal.H, free_mask)
    chi2 = float(np.sum(w * sq)) + (probe_extra(problem)[2] if probe is not None else 0.0)
    dof = max(1, n_res - rank)
    s2 = chi2 / dof
    t = np.zeros((q + 3 * data.n_leds, q + basis.shape[1]))
    t[:q, :q] = np.eye(q)
    t[q:, q:] = basis
    cov_phi = s2 * t @ cov_theta @ t.T
    phi_names = gnames + [
        f"constellation[LED {int(i)}].{c}" for i in data.led_ids for c in ("x", "y", "z")
    ]
    logw = float(np.sum(np.log(w[used]))) * 3.0
    loglik = -0.5 * n_res * (math.log(2 * math.pi * chi2 / n_res) + 1.0) + 0.5 * logw

    frames_rec = data.n_recording_frames
    per_frame = np.full(frames_rec, np.nan)
    cnt = used.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame[data.frame] = np.where(cnt > 0, np.sqrt(np.sum(sq * used, 1) / cnt), np.nan)
        per_led = np.sqrt(np.sum(sq * used, 0) / used.sum(0))
        u_frame = np.sqrt(np.sum(w_noise * sq * used, 1) / np.maximum(3 * cnt, 1) / s2)
    outliers = data.frame[(cnt > 0) & (u_frame > _OUTLIER_U)]
    full_res = np.full((frames_rec, data.n_leds, 3), np.nan)
    full_res[data.frame] = np.where(used[..., None], d, np.nan)
    # weights in the recording's LED columns, so that they can be passed back as `weights=`
    rec_col = {int(i): k for k, i in enumerate(recording.led_ids)}
    full_w = np.zeros((frames_rec, recording.n_leds))
    full_w[np.ix_(data.frame, [rec_col[int(i)] for i in data.led_ids])] = w

    eff = problem.effects
    effects_out = {n: np.asarray(getattr(eff, n)).tolist() for n in free}
    effects_out.update({k: v for k, v in eff.to_dict().items() if k not in effects_out})
    ident = {
        **ident,
        "dropped": ident["dropped"],
        "fixed_parameters": [phi_names[i] for i in range(q) if not free_mask[i]],
    }
    return CalibrationResult(
        camera_from_base=_pose_of(problem.camera_from_base),
        flange_from_tool=_pose_of(problem.flange_from_tool),
        led_ids=np.asarray(data.led_ids),
        constellation=np.asarray(problem.constellation),
        effects=effects_out,
        estimated=free,
        parameter_names=tuple(phi_names),
        covariance=cov_phi,
        residual_rms_m=float(np.sqrt(np.mean(sq[used]))),
        noise_sigma_m=float(np.sqrt(np.mean(sq[used]) / 3.0)),
        gauge=gauge,
        gauge_reference=np.asarray(data.reference),
        identifiability=ident,
        iterations=total_iters,
        converged=bool(converged),
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
        initial=initial,
        unseen_leds=data.unseen_leds,
        robust=robust,
    )


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
    compilation and a Levenberg–Marquardt run per candidate.

    **Arguments:** `weights` as in `fit` (default: `current.weights`).

    **Returns:** ``{effect: {"statistic", "dof", "parameters", "fixed"}}`` (χ² units).
    """
    bad = [e for e in candidates if e not in EFFECT_NAMES]
    if bad:
        raise UserError(f"unknown effect(s) {', '.join(bad)} (known: {', '.join(EFFECT_NAMES)})")
    w = current.weights if weights is None else weights
    st = _setup(recording, EFFECT_NAMES, current, w, chunk, lambda _m: None)
    H, b = st.normal0.H, st.normal0.b
    fixed_now = set(current.identifiability.get("fixed_parameters", []))
    names = st.names_theta
    mine = set(current.estimated)

    def entries(effect):
        return [i for i, n in enumerate(names[: st.q]) if n == effect or n.startswith(effect + "[")]

    base = np.zeros(len(names), bool)
    base[:12] = True
    base[st.q :] = True
    for e in mine:
        for i in entries(e):
            base[i] = names[i] not in fixed_now
    inv_p, rank_p = lm.pinv_scaled(H, base)
    stat_p = float(b @ inv_p @ b)
    out = {}
    for effect in dict.fromkeys(candidates):
        cols = [i for i in entries(effect) if not base[i]]
        free = base.copy()
        free[cols] = True
        droppable = np.zeros(len(names), bool)
        droppable[cols] = True
        free, ident = lm.identifiability(H, st.phi_names, free, droppable)
        inv_f, rank_f = lm.pinv_scaled(H, free)
        out[effect] = {
            "statistic": max(0.0, float(b @ inv_f @ b) - stat_p),
            "dof": int(rank_f - rank_p),
            "parameters": [names[i] for i in cols if free[i]],
            "fixed": [d["parameter"] for d in ident["dropped"]],
        }
    return out


@dataclasses.dataclass
class _Setup:
    """A bundle problem ready for Levenberg–Marquardt (what `fit` and `score_effects`
    share): data, problem, gauge, chunks (`state`), normal-equation and cost functions,
    θ names and the normal equations at the start (`normal0`)."""

    data: CalibrationData
    problem: BundleProblem
    basis: np.ndarray
    probe: Any
    gauge: str
    initial: dict
    free: tuple[str, ...]
    gnames: list[str]
    q: int
    g0: Any
    w_user: np.ndarray
    state: dict
    normal_fn: Callable
    cost_fn: Callable
    probe_extra: Callable
    names_theta: list[str]
    phi_names: list[str]
    droppable: np.ndarray
    normal0: lm.Normal


def _setup(recording, estimate, init, weights, chunk, say) -> _Setup:
    estimate = tuple(dict.fromkeys(estimate))
    bad = [e for e in estimate if e not in EFFECT_NAMES]
    if bad:
        raise UserError(f"unknown effect(s) {', '.join(bad)} (known: {', '.join(EFFECT_NAMES)})")
    free = tuple(n for n in EFFECT_NAMES if n in estimate)

    reference = start = None
    if init is not None and recording.tool is not None:
        reference = _per_tool_led(recording, init.led_ids, init.gauge_reference)
        start = _per_tool_led(recording, init.led_ids, init.constellation)
    tau0 = 0.0 if init is None else init.time_offset
    data = prepare(recording, time_offset=tau0, constellation=reference)
    if start is not None:
        col = {int(i): k for k, i in enumerate(recording.tool.led_ids)}
        start = start[[col[int(i)] for i in data.led_ids]]
    else:
        start = data.reference
    n_joints = data.robot.n_joints
    effects0 = Effects.zeros(n_joints)
    if init is not None:
        for k, v in init.effects.items():
            effects0 = effects0.with_value(k, v)

    say(f"{data.n_frames} frames, {data.n_leds} LEDs: closed-form initialisation")
    if init is None:
        cft, bff, _ = pose_pairs(data, effects0, data.reference)
        z, x = robot_world_hand_eye(cft, bff)
    else:
        z, x = _wxyz_xyz(init.camera_from_base), _wxyz_xyz(init.flange_from_tool)
    initial = {"camera_from_base": _pose_of(z), "flange_from_tool": _pose_of(x)}

    probe = _probe_frames(recording, data, tau0)
    gauge = "probe" if probe is not None else "reference_constellation"
    rows = np.repeat(data.led_seen, 3)  # unseen LEDs: no parameters, kept at the reference
    basis = np.zeros((3 * data.n_leds, 0))
    if probe is not None:
        basis = np.eye(3 * data.n_leds)[:, rows]
    else:
        basis = np.zeros((3 * data.n_leds, 3 * int(data.led_seen.sum()) - 6))
        basis[rows] = _gauge_basis(data.reference[data.led_seen])
    kinematic = any(n in cp.KINEMATIC_EFFECTS for n in free)
    problem = BundleProblem(
        robot=data.robot,
        camera_from_base=jnp.asarray(z),
        flange_from_tool=jnp.asarray(x),
        constellation=jnp.asarray(start),
        gauge_basis=jnp.asarray(basis),
        normals=jnp.asarray(data.normals),
        effects=effects0,
        log_time=jnp.asarray(data.log_time),
        joints=jnp.asarray(data.joints),
        free=free,
        kinematic=kinematic,
        rigid_leds=not any(n in cp.LED_EFFECTS for n in free)
        and all(float(np.max(np.abs(getattr(effects0, n)))) == 0.0 for n in cp.LED_EFFECTS),
    )
    gnames = _global_names(effects0, free)
    q = len(gnames)
    g0 = jnp.zeros(q)
    size = _chunk_size(data.n_frames, chunk)

    if weights is not None:
        w_user = _user_weights(recording, data, weights)
    else:
        w_user = data.seen.astype(float)
    chunks = _chunks(data, np.sqrt(w_user), size)
    if not kinematic:
        fl = cp.fixed_flange_poses(data.robot, effects0, problem.log_time, problem.joints, chunks)
        chunks = eqx.tree_at(lambda f: f.base_from_flange, chunks, fl)

    def probe_extra(pr):
        if probe is None:
            return None
        prk = _kinematic_copy(pr)
        h, b, c = _probe_terms(g0, _jit_view(prk), probe[0], probe[1])
        return np.asarray(h), np.asarray(b), float(c)

    def normal_fn(pr):
        parts = cp.normal_equations(g0, pr.constellation, _jit_view(pr), state["chunks"])
        return lm.assemble(parts, basis, probe_extra(pr))

    def cost_fn(pr):
        c = float(cp.cost(g0, pr.constellation, _jit_view(pr), state["chunks"]))
        extra = probe_extra(pr)
        return c + (extra[2] if extra else 0.0)

    state = {"chunks": chunks}
    names_theta = gnames + [f"constellation.c{j}" for j in range(basis.shape[1])]
    droppable = np.array([i >= 12 and i < q for i in range(len(names_theta))])
    return _Setup(
        data=data,
        problem=problem,
        basis=basis,
        probe=probe,
        gauge=gauge,
        initial=initial,
        free=free,
        gnames=gnames,
        q=q,
        g0=g0,
        w_user=w_user,
        state=state,
        normal_fn=normal_fn,
        cost_fn=cost_fn,
        probe_extra=probe_extra,
        names_theta=names_theta,
        phi_names=_phi_names_for(names_theta, q, basis, data),
        droppable=droppable,
        normal0=normal_fn(problem),
    )


def _jit_view(problem: BundleProblem) -> BundleProblem:
    """The problem without its gauge basis (whose shape varies with the LEDs seen), so
    that the jitted kernels compile once for recordings of the same shape."""
    return eqx.tree_at(lambda p: p.gauge_basis, problem, jnp.zeros((0, 0)))


def _kinematic_copy(problem: BundleProblem) -> BundleProblem:
    if problem.kinematic:
        return problem
    return BundleProblem(
        **{
            f.name: getattr(problem, f.name)
            for f in dataclasses.fields(problem)
            if f.name != "kinematic"
        },
        kinematic=True,
    )


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


def _optimistix(problem, chunks, free_mask, q, basis, normal_fn, max_iter):
    """`optx.LevenbergMarquardt` on the pure residuals of all frames (materialises J)."""
    import optimistix as optx

    frames = jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), chunks)
    mask_g = jnp.asarray(free_mask[:q], float)
    mask_c = jnp.asarray(free_mask[q:], float)

    def fn(params, args):
        params = BundleParams(
            camera_from_base=params.camera_from_base * mask_g[:6],
            flange_from_tool=params.flange_from_tool * mask_g[6:12],
            constellation=params.constellation * mask_c,
            effects=params.effects * mask_g[12:],
        )
        return residual_fn(params, args)

    y0 = BundleParams(jnp.zeros(6), jnp.zeros(6), jnp.zeros(basis.shape[1]), jnp.zeros(q - 12))
    sol = optx.least_squares(
        fn,
        optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12),
        y0,
        args=(problem, frames),
        max_steps=max_iter,
        throw=False,
    )
    y = sol.value
    delta = (
        np.concatenate(
            [
                np.asarray(y.camera_from_base),
                np.asarray(y.flange_from_tool),
                np.asarray(y.effects),
                np.asarray(y.constellation),
            ]
        )
        * free_mask
    )
    problem = lm.recentre(problem, delta, q)
    steps = int(sol.stats.get("num_steps", 0))
    return problem, normal_fn(problem), steps, bool(sol.result == optx.RESULTS.successful)
