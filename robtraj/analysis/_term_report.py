"""The report of a named dictionary term (`Step.term`): its variable, function,
coefficients with σ, its description in words and where in the recording it acts."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import numpy as np

from ..model import amplitude_phase, describe, gravity_torque, term
from ..recording import Recording


def _term_block(res, effect: str) -> tuple[np.ndarray, np.ndarray]:
    """Fitted coefficients of dictionary term `effect` and their covariance: of those
    the quoted σ takes the largest of (`CalibrationResult.quoted`: Gauss–Newton,
    cluster-robust, model-error field), the one of the largest trace."""
    t = term(effect)
    names = [f"{effect}.{c}" for c in t.components]
    idx = [res.parameter_names.index(n) if n in res.parameter_names else -1 for n in names]
    values = np.asarray(res.effects[effect], float)
    cov = np.zeros((t.size, t.size))
    ok = [k for k, i in enumerate(idx) if i >= 0]
    if ok:
        sel = [idx[k] for k in ok]
        covs = (res.covariance, res.covariance_robust, res.covariance_field)
        blocks = [np.asarray(c)[np.ix_(sel, sel)] for c in covs if c is not None]
        cov[np.ix_(ok, ok)] = max(blocks, key=lambda b: float(np.trace(b)))
    return values, cov


def _term_inputs(rec: Recording, tau: float, threshold: float):
    """Per tracker frame: logged joint angles at t + τ, velocity signs (0 slower than
    `threshold` [rad/s]), gravity torques."""
    import jax.numpy as jnp

    from ..model import interpolate_joints, motion_sign, robot_from_log

    robot = robot_from_log(rec.robot)
    lt, lj = np.asarray(rec.robot.time, float), np.asarray(rec.robot.joints, float)
    t = np.asarray(rec.time, float) + tau
    q = interpolate_joints(jnp.asarray(lt), jnp.asarray(lj), jnp.asarray(t))
    return q, jnp.asarray(motion_sign(lt, lj, t, threshold)), _gravity_torques(robot, q)


@eqx.filter_jit
def _gravity_torques(robot, q):
    """Gravity torque [N·m] per frame of joint angles `q` `(frames, joints)`."""
    return jax.vmap(gravity_torque, in_axes=(None, 0))(robot, q)


@eqx.filter_jit
def _term_values(fn, c, q, sign, torque):
    """A joint term's angle error [rad] per frame, `fn(q, sign, torque) @ c`."""
    return jax.vmap(lambda a, b, d: fn(a, b, d) @ c)(q, sign, torque)


def _where_it_acts(rec: Recording, res, effect: str, angles: np.ndarray) -> dict[str, Any]:
    """Where in the recording term `effect` acts: the range of its variable that the
    recording covers and the share of frames (joint terms; observations for LED terms)
    where the fitted term is at least half its peak."""
    import jax.numpy as jnp

    t = term(effect)
    c = jnp.asarray(res.effects[effect], float)
    if t.kind == "joint":
        q, sign, torque = _term_inputs(rec, res.time_offset, res.motion_threshold)
        size = np.abs(np.asarray(_term_values(t.fn, c, q, sign, torque)))
        # a constructed term: the range of its first factor's signal
        f = t.factors[0] if t.factors else None
        by_torque = f is not None and f.signal == "tau"
        qj = np.asarray(torque if by_torque else q)[:, t.joint if f is None else f.joint]
        where = {
            "variable_range": [float(qj.min()), float(qj.max())],
            "unit": "N·m" if by_torque else "rad",
        }
    else:
        th = np.where(np.isfinite(angles), angles, 0.0)
        y = np.nan_to_num(np.asarray(rec.positions, float))
        y = np.where(np.isfinite(angles)[..., None], y, 1.0)
        # a term's size does not depend on which unit direction it acts along
        n = y / np.linalg.norm(y, axis=-1, keepdims=True)
        disp = np.asarray(t.fn(jnp.asarray(y), jnp.asarray(n), jnp.asarray(th)) @ c)
        size = np.linalg.norm(disp, axis=-1)[np.isfinite(angles)]
        ok = angles[np.isfinite(angles)]
        where = {"variable_range": [float(ok.min()), float(ok.max())], "unit": "rad"}
    peak = float(np.max(size)) if size.size else 0.0
    where["peak"] = peak
    where["share_above_half_peak"] = float(np.mean(size >= 0.5 * peak)) if peak > 0 else 0.0
    return where


def term_report(
    rec: Recording, res, effect: str, angles: np.ndarray, interval=None
) -> dict[str, Any] | None:
    """`steps[].term`: a dictionary term's variable, function, coefficients with σ, its
    description in words and where it acts (None for a library effect); for a term of the
    motion sign, the speed below which the joints count as at rest and its profile
    interval (`interval`, [rad/s])."""
    t = term(effect)
    if t is None:
        return None
    values, cov = _term_block(res, effect)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    out = {
        "name": effect,
        "kind": t.kind,
        "variable": t.variable,
        "function": t.function,
        "unit": t.unit,
        "parameters": {
            c: {"value": float(v), "sigma": float(e)} for c, v, e in zip(t.components, values, sig)
        },
        "words": describe(t, values, cov),
        "acts": _where_it_acts(rec, res, effect, angles),
    }
    if t.harmonic:
        a, sa, phi, sp = amplitude_phase(values, cov)
        out.update(amplitude=a, amplitude_sigma=sa, phase_rad=phi, phase_sigma_rad=sp)
    if t.motion:
        d = res.motion_threshold
        out["motion_threshold_rad_s"] = d
        out["motion_threshold_interval_rad_s"] = None if interval is None else list(interval)
        if interval is None:
            span = ""
        elif interval[0] == interval[1]:
            span = " (Δχ² ≤ 1 within one step of the profile, 2^(1/16))"
        else:
            span = f" (Δχ² ≤ 1: {interval[0]:.3g} to {interval[1]:.3g})"
        out["words"] += f"; at rest below {d:.3g} rad/s{span}"
    return out
