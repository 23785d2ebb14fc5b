"""Where to measure to tell two equally supported models apart: static robot poses at
which their predictions of the LEDs differ most against the recording's noise.

Two models that fit a recording equally well agree over the joint angles it reached;
they part where it did not go. The candidates are the recording's own joint
configurations (evenly spread, as for `robtraj calibrate`'s next poses) with one joint at a time turned by `TURNS` (inside the
robot's joint limits where it has them). A candidate counts where at least
`MIN_LEDS` LEDs would be seen (emission angle and camera distance inside what the
recording saw, under the first model). With `a` taken as the truth, a pose is worth
what the rival `b` cannot follow once refitted (Atkinson and Fedorov's T-optimal design,
linearised): the difference ``d = p_a − p_b`` of the predicted LED positions, weighted by
one static dwell of `DWELL_S` (frames / σ², the recording's noise model per axis), less
what a change of `b`'s own effect parameters absorbs, those held by the recording to its
Gauss–Newton information ``H`` and by the poses chosen: ``T = dᵀWd − gᵀ(H + JᵀWJ)⁻¹g``,
``g = JᵀWd``, `J` the derivative of `b`'s prediction in its effect parameters (central
differences). Poses are chosen greedily, each the one that raises `T` of all chosen the
most (a rival can match one pose by its parameters, not several far apart).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..estimate import DWELL_S, MIN_LEDS, base_configurations, distances_seen
from ..model import (
    effect_component_names,
    emission_angle,
    pose_se3,
    predict_tool_poses,
    robot_from_log,
)

#: [rad] the turns of one joint that make the candidates
TURNS = np.deg2rad([-60.0, -40.0, -20.0, 20.0, 40.0, 60.0])


@dataclasses.dataclass(frozen=True)
class SeparatingPoses:
    """Static poses that tell model `a` from model `b`, in the order chosen: `joints`
    `(n, joints)` [rad], the LEDs each would show (`leds_seen`), and `chi2` what one
    dwell of `dwell_s` at each adds to the χ² `b` cannot fit after refitting when `a` is
    the truth; `chi2_recording` the difference of the two fits' χ² on the recording
    itself (how little it tells them apart)."""

    a: str
    b: str
    joints: np.ndarray
    leds_seen: np.ndarray
    chi2: np.ndarray
    chi2_recording: float
    dwell_s: float = DWELL_S

    def to_json(self) -> dict[str, Any]:
        return {
            "models": [self.a, self.b],
            "joints_rad": np.asarray(self.joints).tolist(),
            "leds_seen": [int(k) for k in self.leds_seen],
            "chi2_per_dwell": [float(c) for c in self.chi2],
            "chi2_recording": float(self.chi2_recording),
            "dwell_s": self.dwell_s,
        }


def candidates(joints: np.ndarray, limits: np.ndarray | None) -> np.ndarray:
    """`(K, joints)` configurations [rad]: the logged `joints` evenly spread
    (`base_configurations`) with one joint turned by each of `TURNS`, those inside
    `limits` `(joints, 2)`."""
    base = base_configurations(joints)
    j = base.shape[1]
    steps = (np.eye(j)[:, None, :] * TURNS[None, :, None]).reshape(-1, j)
    out = (base[:, None, :] + steps[None]).reshape(-1, j)
    if limits is not None:
        lim = np.asarray(limits, float)
        out = out[np.all((out >= lim[:, 0]) & (out <= lim[:, 1]), axis=1)]
    return out


def _leds(robot, calib, q: jax.Array, normals: np.ndarray):
    """Camera-frame LED positions `(K, m, 3)` [m] and emission angles `(K, m)` [rad]
    that `calib` predicts for static poses at `q` (no motion, no drift)."""
    zero = jnp.zeros_like(q)
    tool = predict_tool_poses(
        robot,
        calib.effects_module(q.shape[1]),
        pose_se3(calib.camera_from_base),
        pose_se3(calib.flange_from_tool),
        q,
        zero,
        jnp.zeros(q.shape[0], q.dtype),
        zero,
    )
    rot = jax.vmap(lambda t: t.rotation().as_matrix())(tool)
    leds = (
        jnp.einsum("kij,mj->kmi", rot, jnp.asarray(calib.constellation))
        + tool.translation()[:, None, :]
    )
    axes = jnp.einsum("kij,mj->kmi", rot, jnp.asarray(normals))
    return np.asarray(leds), np.asarray(emission_angle(leds, axes))


def separating_poses(
    rec,
    noise,
    angles: np.ndarray,
    a: tuple[str, Any],
    b: tuple[str, Any],
    n: int = 6,
) -> SeparatingPoses | None:
    """The `n` static poses that tell the fitted models `a` and `b` (``(name,
    CalibrationResult)``, fitted to `rec`) apart best (module docstring); `noise` the
    recording's `NoiseModel` and `angles` `(N, M)` [rad] its observations' emission
    angles (the range a candidate must stay inside). None when the recording has no
    LED normals or no candidate would show `MIN_LEDS` LEDs."""
    if rec.tool is None or rec.tool.normals is None or rec.robot is None:
        return None
    (name_a, fit_a), (name_b, fit_b) = a, b
    robot = robot_from_log(rec.robot)
    normals = _normals(rec, fit_a.led_ids)
    limits = None if robot.joint_limits is None else np.asarray(robot.joint_limits)
    q = candidates(np.asarray(rec.robot.joints), limits)
    leds_a, theta = _leds(robot, fit_a, jnp.asarray(q), normals)
    leds_b, _ = _leds(robot, fit_b, jnp.asarray(q), normals)
    seen_angle = float(np.nanmax(angles))
    dist = np.linalg.norm(leds_a, axis=-1)
    lo, hi = distances_seen(rec)
    seen = (theta <= seen_angle) & (dist >= lo) & (dist <= hi)
    ok = seen.sum(1) >= MIN_LEDS
    if not ok.any():
        return None
    frames = max(1.0, DWELL_S / float(np.median(np.diff(rec.time))))
    var = noise.variance_at(np.where(seen, theta, 0.0), np.where(seen, dist, lo),
                            _levels(noise, fit_a.led_ids))  # fmt: skip
    w = np.repeat(np.where(seen, frames / var, 0.0), 3, axis=1)[ok]  # (K, m·3)
    d = (leds_a - leds_b).reshape(q.shape[0], -1)[ok]
    jac, info = _effect_jacobian(robot, fit_b, name_b, q[ok], normals)
    chosen, gain = _greedy(d, w, jac, info, q[ok], n)
    return SeparatingPoses(
        name_a,
        name_b,
        q[ok][chosen],
        seen[ok][chosen].sum(1),
        gain,
        abs(float(fit_a.chi2 - fit_b.chi2)),
    )


def _effect_jacobian(robot, fit, effect: str, q: np.ndarray, normals: np.ndarray):
    """The derivative `(K, m·3, p)` of `fit`'s predicted LED positions at `q` in the `p`
    components of its `effect` (central differences of one σ), and their information
    `(p, p)` from the recording (the inverse of their Gauss–Newton covariance)."""
    value = np.asarray(fit.effects[effect], float)
    names = effect_component_names(effect, value.shape)
    index = [fit.parameter_names.index(k) for k in names]
    cov = np.asarray(fit.covariance)[np.ix_(index, index)]
    step = np.sqrt(np.clip(np.diag(cov), 1e-30, None))
    cols = []
    for k in range(len(names)):
        out = []
        for sign in (1.0, -1.0):
            v = value.ravel().copy()
            v[k] += sign * step[k]
            moved = dataclasses.replace(
                fit, effects={**fit.effects, effect: v.reshape(value.shape)}
            )
            out.append(_leds(robot, moved, jnp.asarray(q), normals)[0].reshape(q.shape[0], -1))
        cols.append((out[0] - out[1]) / (2 * step[k]))
    return np.stack(cols, -1), np.linalg.pinv(cov)


def _greedy(d, w, jac, info, q, n: int):
    """Indices of up to `n` candidates chosen one by one, each raising the T criterion
    (module docstring) of those chosen the most, and each one's gain in it."""
    jw = jac * w[..., None]  # (K, r, p)
    a_k = np.einsum("krp,krs->kps", jw, jac)  # JᵀWJ per candidate
    b_k = np.einsum("krp,kr->kp", jw, d)  # JᵀWd
    c_k = np.einsum("kr,kr->k", w * d, d)  # dᵀWd
    a, b, c, t = info.copy(), np.zeros(info.shape[0]), 0.0, 0.0
    chosen: list[int] = []
    gains: list[float] = []
    for _ in range(min(n, d.shape[0])):
        aa, bb = a[None] + a_k, b[None] + b_k
        # pinv: a component neither the recording nor any pose moves stays at zero
        tt = c + c_k - np.einsum("kp,kps,ks->k", bb, np.linalg.pinv(aa, hermitian=True), bb)
        for k in chosen:  # a configuration once
            tt[np.max(np.abs(q - q[k]), axis=1) <= 1e-3] = -np.inf
        best = int(np.argmax(tt))
        if not np.isfinite(tt[best]):
            break
        chosen.append(best)
        gains.append(float(tt[best] - t))
        a, b, c, t = a + a_k[best], b + b_k[best], c + c_k[best], float(tt[best])
    return np.asarray(chosen, int), np.asarray(gains)


def _normals(rec, led_ids) -> np.ndarray:
    row = {int(i): k for k, i in enumerate(np.asarray(rec.tool.led_ids))}
    return np.asarray(rec.tool.normals, float)[[row[int(i)] for i in np.asarray(led_ids)]]


def _levels(noise, led_ids) -> np.ndarray:
    """The noise model's level row of each of `led_ids` (0 where it has none)."""
    row = {int(i): k for k, i in enumerate(np.asarray(noise.led_ids))}
    return np.array([row.get(int(i), 0) for i in np.asarray(led_ids)])
