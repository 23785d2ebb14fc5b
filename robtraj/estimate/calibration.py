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
  the normal equations accumulated in chunks of frames (no Jacobian of the whole
  recording), read from the recording block by block at every step (`_calib_frames`:
  memory independent of the recording's length; the weights recomputed per block).
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

`fit` reads as its steps, each a function of the module that owns it, in the order the
recording's data pass through them (each module imports only those before it):
`_calib_setup` (the effects in the problem, `_calib_parameters`; the observations,
`_calib_data`, with the noise model, `_observation_noise`, estimated on a background
thread meanwhile; the start, `_calib_init`; the problem, `_calib_problem`, built and its
kernels compiled on the compiling thread, `_compile_ahead`, with the clusters of the
robust covariance, `_calib_clusters`) → `_calib_solves` (the weighted solve and the
robust passes, through the engine `_solve`) → `_calib_uncertainty` (identifiability and
covariances, `_uncertainty`; the residuals meanwhile, `_calib_residuals`) →
`_next_poses` → `_calib_result`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from ..model import pose_se3
from ..recording import Pose, Recording
from . import _calib_problem as cp
from ._calib_clusters import (
    CLUSTER_SPAN as CLUSTER_SPAN,
    MAX_CLUSTERS as MAX_CLUSTERS,
    ROBUST_MAX_GLOBAL as ROBUST_MAX_GLOBAL,
)
from ._calib_init import robot_world_hand_eye
from ._calib_parameters import check_names, effect_of, library_space
from ._calib_problem import BundleData, BundleProblem, Frames, bundle_normal, residuals
from ._calib_result import (
    READABLE_VERSIONS,
    SCHEMA_VERSION,
    CalibrationResult,
    calibration_result,
)
from ._calib_setup import setup
from ._calib_solves import (
    HOLDABLE as HOLDABLE,
    ROBUST as ROBUST,
    robust_passes,
    solve_settings,
    weighted_solve,
)
from ._calib_uncertainty import WEAK_SIGMA as WEAK_SIGMA, uncertainty
from ._clock import clock_effects
from ._next_poses import suggested_poses
from ._uncertainty import covariance, identifiability

__all__ = [
    "BundleData",
    "BundleProblem",
    "CalibrationResult",
    "READABLE_VERSIONS",
    "SCHEMA_VERSION",
    "Frames",
    "align_to_gauge",
    "error_against",
    "bundle_normal",
    "fit",
    "predict_residuals",
    "residuals",
    "robot_world_hand_eye",
    "score_effects",
]


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
    fft = pose_se3(flange_from_tool) @ g.inverse()
    return pg, Pose.from_wxyz_xyz(fft.wxyz_xyz)


def error_against(result: CalibrationResult, truth, led_ids) -> np.ndarray:
    """`result`'s error against `truth` (camera←base, flange←tool and constellation of
    LEDs `led_ids`, e.g. a simulation's `Truth`), in `result`'s gauge: camera←base and
    flange←tool as SE(3) tangents ``log(truth⁻¹·fit)`` (translation [m], rotation [rad];
    6 each), then the constellation `(leds·3,)` [m] in `result`'s LED order."""
    p_true, fft_true = align_to_gauge(result, truth.constellation, truth.flange_from_tool, led_ids)
    return np.concatenate(
        [
            np.asarray(
                (
                    pose_se3(truth.camera_from_base).inverse() @ pose_se3(result.camera_from_base)
                ).log()
            ),
            np.asarray((pose_se3(fft_true).inverse() @ pose_se3(result.flange_from_tool)).log()),
            (np.asarray(result.constellation) - p_true).reshape(-1),
        ]
    )


# ----------------------------------------------------------------------------- fit


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
    per_observation: bool = True,
    one_step: bool = False,
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
    - `per_observation`: keep the `(frames, leds)` arrays in the result (`residuals`,
      `weights`); False for a recording of any length (`recording` opened with
      `robtraj.open_recording`: the fit reads its frames block by block, in memory
      independent of its length).
    - `one_step`: one Gauss–Newton step from the start instead of a solve to
      convergence (`robtraj.estimate.gauss_newton_step`): for a start at the optimum of
      a problem that the fit's `weights` change only a little (the discrepancy search's
      held-out fits, which start from the fit to the whole recording), that optimum to
      second order in the step, for one pass over the recording instead of one per
      solver step. No robust loss.

    **Returns:** a `CalibrationResult` (`converged` False, with the reason in
    `convergence`, when a solve stopped before its criterion held). Raises `UserError`
    for unusable input.
    """
    say = progress or (lambda _msg: None)
    how = solve_settings(solver, max_iter, robust, hold, one_step)
    estimate = tuple(dict.fromkeys((*clock_effects(recording.robot), *estimate)))
    st = setup(
        recording,
        estimate,
        init,
        weights,
        chunk,
        say,
        space=space,
        motion=motion_threshold,
        solver=how.solver,
        clustered=robust_sigma,
        per_observation=per_observation,
    )
    solved = weighted_solve(st, how, say)
    solved = robust_passes(st, solved, how, say)
    unc, res = uncertainty(st, solved, robust_sigma and st.clustered, say)
    unc = suggested_poses(recording, st, solved, unc, res, suggest, say)
    return calibration_result(recording, st, solved, unc, res, how.robust)


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
    check_names(candidates)
    w = current.weights if weights is None else weights
    space = library_space(candidates, current.estimated, tuple(current.effects))
    st = setup(recording, space, current, w, chunk, lambda _m: None, start_only=True)
    H = st.h0
    b = np.asarray(st.normal0[1])
    fixed_now = set(current.identifiability.get("fixed_parameters", []))
    names = st.names_theta
    mine = set(current.estimated)

    def entries(effect):
        return [i for i, n in enumerate(names[12 : st.q], 12) if effect_of(n) == effect]

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
    st = setup(recording, (), calibration, None, None, lambda _m: None, False, space)
    data = st.data
    out = np.full((data.n_recording_frames, data.n_leds, 3), np.nan)

    def visit(block, d, _theta):
        seen = data.seen[block.a : block.b]
        out[data.frame[block.a : block.b]] = np.where(seen[..., None], d, np.nan)

    cp.over_residuals(st.bundle, st.q, visit)
    col = {int(i): k for k, i in enumerate(data.led_ids)}
    keep = [col.get(int(i)) for i in calibration.led_ids]
    return np.stack(
        [out[:, k] if k is not None else np.full(out.shape[::2], np.nan) for k in keep], 1
    )
