"""What to measure next: the static robot poses that would best determine what a
calibration leaves weak or undetermined (greedy D-optimal design on the engine's normal
matrix).

Candidates are the recording's own joint configurations with the wrist (last three
joints) turned by ±20° and ±40°, one joint at a time and in pairs: poses near ones the
robot reached in this setup, reoriented — what separates flange←tool from camera←base.
A candidate counts only where at least four LEDs the calibration determined would be
seen: emission angle and distance inside what the recording saw. Each would add the information of one static
dwell (`DWELL_S` at the recording's frame rate), with the recording's noise model as
weights. Greedily, the candidate that raises ``log det`` of the column-scaled free
normal matrix (plus a small ridge, so that null directions count) the most is taken,
then the next given it, and so on.

A calibration asks for them (`suggested_poses`) when it leaves a rigid-transform
parameter weak or a global parameter undetermined.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..model import emission_angle, flange_poses
from ..recording import Recording
from ._calib_problem import BundleData, Frames, chunk_terms, h_in_theta, tool_poses
from ._calib_residuals import Quantile, Residuals
from ._calib_setup import Setup
from ._calib_solves import Solved
from ._calib_uncertainty import Uncertainty
from ._chunks import over_frames
from ._noise import NoiseModel
from ._uncertainty import column_scale, covariance, identifiability

#: [s] of static dwell each suggested pose stands for
DWELL_S = 1.0
#: logged joint configurations the candidates start from (evenly spread)
BASE_CONFIGURATIONS = 40
#: wrist turns [rad] of the candidates
WRIST_TURNS = np.deg2rad([-40.0, -20.0, 20.0, 40.0])
#: ridge of the D-optimal criterion, relative to the largest eigenvalue
RIDGE = 1e-9
MIN_LEDS = 4


@dataclasses.dataclass(frozen=True)
class NextPoses:
    """Suggested static poses, best first: `joints` `(n, joints)` [rad], `leds_seen`
    `(n,)` the LEDs each would show; `sigma_before` the σ of the `watched` parameters now
    and `sigma_after[k]` after adding the first k + 1 poses (inf: not determined)."""

    joints: np.ndarray
    leds_seen: np.ndarray
    watched: tuple[str, ...]
    sigma_before: dict[str, float]
    sigma_after: list[dict[str, float]]
    dwell_s: float

    def to_json(self) -> dict[str, Any]:
        def clean(d):
            return {k: (v if np.isfinite(v) else None) for k, v in d.items()}

        return {
            "joints_rad": np.asarray(self.joints).tolist(),
            "leds_seen": [int(x) for x in self.leds_seen],
            "dwell_s": self.dwell_s,
            "sigma_before": clean(self.sigma_before),
            "sigma_after": [clean(d) for d in self.sigma_after],
        }


def base_configurations(joints: np.ndarray, n: int = BASE_CONFIGURATIONS) -> np.ndarray:
    """Up to `n` of the logged joint configurations `joints` `(N, joints)` [rad], evenly
    spread over the log: where candidate poses start from."""
    q = np.asarray(joints, float)
    return q[np.unique(np.linspace(0, q.shape[0] - 1, n).round().astype(int))]


def candidate_joints(joints: np.ndarray, n_base: int = BASE_CONFIGURATIONS) -> np.ndarray:
    """`(K, joints)` candidate configurations [rad] from logged ones `joints`."""
    q = np.asarray(joints, float)
    base = base_configurations(q, n_base)
    wrist = list(range(max(0, q.shape[1] - 3), q.shape[1]))
    steps = []
    for k in (1, 2):
        for axes in itertools.combinations(wrist, k):
            for turns in itertools.product(WRIST_TURNS, repeat=k):
                d = np.zeros(q.shape[1])
                d[list(axes)] = turns
                steps.append(d)
    return (base[:, None, :] + np.array(steps)[None]).reshape(-1, q.shape[1])


@eqx.filter_jit
def _observe(bundle: BundleData, q: jax.Array):
    """LED positions `(K, m, 3)` [m] and emission angles `(K, m)` at configurations `q`."""
    m = bundle.problem.constellation.shape[0]
    problem, frames = _static_problem(bundle, q, jnp.zeros((q.shape[0], m), q.dtype))
    g = jnp.zeros(_q_count(bundle), q.dtype)
    tool, eff = tool_poses(g, problem, frames)
    rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool)
    p = problem.constellation
    leds = jnp.einsum("cij,mj->cmi", rot, p) + tool.translation()[:, None, :]
    nrm = jnp.einsum("cij,mj->cmi", rot, problem.normals)
    return leds, emission_angle(leds, nrm)


def _q_count(bundle: BundleData) -> int:
    eff = bundle.problem.effects
    return 12 + sum(int(np.size(eff.get(n))) for n in bundle.problem.free)


def _static_problem(bundle: BundleData, q: jax.Array, sqrt_w: jax.Array):
    """The problem at its current values with `q` as the joint log (one static frame
    per configuration, no clock offset, no temperature change) and those frames."""
    problem = bundle.problem
    k = q.shape[0]
    eff = eqx.tree_at(lambda e: e.time_offset, problem.effects, jnp.zeros(()))
    problem = eqx.tree_at(
        lambda pr: (pr.effects, pr.log_time, pr.joints),
        problem,
        (eff, jnp.arange(k, dtype=q.dtype), q),
    )
    fl = flange_poses(problem.robot, eff, q, jnp.zeros_like(q)).wxyz_xyz
    m = problem.constellation.shape[0]
    frames = Frames(
        time=jnp.arange(k, dtype=q.dtype),
        direction=jnp.zeros_like(q),
        moving=jnp.zeros_like(q),
        drift=jnp.zeros(k, q.dtype),
        measured=jnp.zeros((k, m, 3), q.dtype),
        sqrt_weight=sqrt_w,
        base_from_flange=fl,
    )
    return problem, frames


@eqx.filter_jit
def _information(bundle: BundleData, q: jax.Array, sqrt_w: jax.Array):
    """Normal matrix `(K, P, P)` in θ of one frame at each configuration."""
    problem, frames = _static_problem(bundle, q, sqrt_w)
    g = jnp.zeros(_q_count(bundle), q.dtype)
    one = jax.tree_util.tree_map(lambda a: a[:, None], frames)  # K chunks of one frame

    def h_of(f):
        hgg, hgp, hpp, *_ = chunk_terms(g, problem.constellation, problem, f)
        return h_in_theta(hgg, hgp, hpp, bundle.basis)

    return jax.vmap(h_of)(one)


def next_poses(
    bundle: BundleData,
    h: np.ndarray,
    free: np.ndarray,
    s2: float,
    names: list[str],
    watched: list[str],
    variance_at,
    joints: np.ndarray,
    frame_rate: float,
    seen_angle: float,
    seen_distance: tuple[float, float],
    known: np.ndarray,
    n: int = 6,
) -> NextPoses | None:
    """Greedy D-optimal choice of `n` static poses (module docstring).

    `bundle` at the optimum, `h` its normal matrix in θ and `free` the free mask, `s2`
    the variance factor of the covariance, `names` θ's names and `watched` the ones to
    report; `variance_at(theta, distance, led)` the per-axis noise variance [m²];
    `joints` the logged joint configurations; `seen_angle` [rad] and `seen_distance` [m]
    what the recording saw; `known` `(m,)` the LEDs whose position the calibration
    determined (an LED it never saw would bring parameters of its own, so it is not
    counted). None when no candidate would show `MIN_LEDS` LEDs.
    """
    q = jnp.asarray(candidate_joints(joints))
    leds, theta = (np.asarray(a) for a in _observe(bundle, q))
    dist = np.linalg.norm(leds, axis=-1)
    lo, hi = seen_distance
    seen = (theta <= seen_angle) & (dist >= lo) & (dist <= hi) & np.asarray(known, bool)
    ok = seen.sum(1) >= MIN_LEDS
    if not ok.any():
        return None
    q, seen, theta, dist = q[ok], seen[ok], theta[ok], dist[ok]
    led = np.broadcast_to(np.arange(seen.shape[1]), seen.shape)
    var = variance_at(np.where(seen, theta, 0.0), np.where(seen, dist, lo), led)
    frames = max(1.0, DWELL_S * frame_rate)
    sqrt_w = np.where(seen, np.sqrt(frames / var), 0.0)
    info = np.array(_information(bundle, q, jnp.asarray(sqrt_w)))
    tau = [i for i, name in enumerate(names) if name == "time_offset"]
    info[:, tau, :] = 0.0  # a static pose says nothing of the clock offset
    info[:, :, tau] = 0.0

    idx = np.flatnonzero(free)
    d = column_scale(h)[idx]
    scale = np.outer(d, d)
    a = h[np.ix_(idx, idx)] / scale
    ridge = RIDGE * float(np.linalg.eigvalsh(a)[-1]) * np.eye(idx.size)
    cand = info[:, idx][:, :, idx] / scale
    chosen: list[int] = []
    total = a.copy()
    for _ in range(min(n, cand.shape[0])):
        _, logdet = np.linalg.slogdet(total[None] + cand + ridge[None])
        logdet[chosen] = -np.inf
        best = int(np.argmax(logdet))
        chosen.append(best)
        total = total + cand[best]

    def sigmas(hh):
        _, ident = identifiability(hh, names, free, np.zeros(len(names), bool))
        cov, _ = covariance(hh, free, s2)
        sig = np.sqrt(np.clip(np.diag(cov), 0, None))
        out = {w: float(sig[names.index(w)]) for w in watched}
        for w in ident["undetermined"]:
            if w in out:
                out[w] = float("inf")
        return out

    after, hh = [], np.asarray(h, float)
    for c in chosen:
        hh = hh + info[c]
        after.append(sigmas(hh))
    return NextPoses(
        joints=np.asarray(q)[chosen],
        leds_seen=seen[chosen].sum(1),
        watched=tuple(watched),
        sigma_before=sigmas(np.asarray(h, float)),
        sigma_after=after,
        dwell_s=DWELL_S,
    )


def suggested_poses(
    recording: Recording,
    st: Setup,
    solved: Solved,
    unc: Uncertainty,
    res: Residuals,
    n: int,
    say: Callable[[str], None],
) -> Uncertainty:
    """`unc` with up to `n` poses that would determine best what the calibration leaves
    weak or undetermined (``identifiability["next_poses"]``, `next_poses`), with the
    recording's noise model (or one variance from the weights), its joint log, frame
    rate and the distances it saw; `unc` itself when nothing is to be determined or `n`
    is 0."""
    ident = unc.identifiability
    # poses are suggested for the global parameters (rigid transforms, effects); an
    # undetermined LED coordinate needs that LED seen, not another pose
    watched = list(
        dict.fromkeys(
            [w["parameter"] for w in ident["weak"]]
            + [u for u in ident["undetermined"] if u in st.names_theta[: st.q]]
        )
    )
    if not (watched and n):
        return unc
    say("poses that would determine " + ", ".join(watched))
    data = st.data
    rate = 1.0 / float(np.median(np.diff(data.time))) if data.n_frames > 1 else 1.0
    nxt = next_poses(
        solved.bundle.with_frames(None), unc.h, solved.free, unc.s2, st.names_theta, watched,
        _variance_model(st.noise, data.led_ids, res.mean_weight), data.joints, rate,
        res.seen_angle, distances_seen(recording), data.led_seen, n,
    )  # fmt: skip
    next_json = None if nxt is None else nxt.to_json()
    return dataclasses.replace(unc, identifiability={**ident, "next_poses": next_json})


def distances_seen(recording: Recording) -> tuple[float, float]:
    """The range of camera distances [m] the recording's LEDs were seen at (1st to 99th percentile,
    widened by 5 %), in two passes over its frames."""
    n = [0]

    def count(_a, x):
        n[0] += int(np.isfinite(x[..., 0]).sum())

    over_frames(recording.positions, count)
    lo, hi = Quantile(n[0], 0.99), Quantile(n[0], 0.99)

    def keep(_a, x):
        dist = np.linalg.norm(x[np.isfinite(x[..., 0])], axis=-1)
        hi.add(dist)
        lo.add(-dist)

    over_frames(recording.positions, keep)
    return -0.95 * lo.value(), 1.05 * hi.value()


def _variance_model(noise: NoiseModel | None, led_ids: np.ndarray, mean_weight: float):
    """``variance_at(theta, distance, led)`` [m²] of `next_poses`: the noise model's, or
    one variance from the observations' mean weight without one."""
    if noise is not None:
        row = {int(i): k for k, i in enumerate(noise.led_ids)}
        level = np.array([row.get(int(i), 0) for i in led_ids])

        def variance_at(theta, r, led):
            return noise.variance_at(theta, r, level[led])
    else:
        v = float(1.0 / mean_weight)

        def variance_at(theta, r, led):
            return np.full(np.shape(theta), v)

    return variance_at
