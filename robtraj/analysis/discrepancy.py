"""Discrepancy discovery (DESIGN section 7): what is the nominal model missing?

Fit the nominal model (bundle calibration); compare prediction and measurement; localise
the disagreement (time, program segment, joint angles, speed and acceleration, LED,
emission angle); score every candidate effect of the library at once with Rao's score
test (the Gauss–Newton predicted χ² decrease of adding it, χ²(k) under the null) and
BIC, with the noise level estimated from the data's static segments (not from the fit's
own residual, which contains what is missing); refit with the best significant one and
name it when the refit's likelihood-ratio test confirms it; repeat until nothing
significant remains; finally test whether structured residual is left and, if so,
report where it lives — never forcing a library name on it.

The **gap** is the RMS of the systematic disagreement with the noise taken out:
``sqrt(max(0, mean|r|² − mean 3σ̂²))`` over all LED observations [m].
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np
from scipy import stats

from .._errors import UserError
from ..estimate import observation_angles, observation_noise
from ..model import (
    LIBRARY,
    MOTION_THRESHOLD,
    amplitude_phase,
    describe,
    dictionary,
    gravity_torque,
    is_effect,
    term,
)
from ..recording import Recording

#: significance of a candidate effect, before the Bonferroni division by the candidates
ALPHA = 0.01
#: significance of residual structure against one variable, before Bonferroni
ALPHA_STRUCTURE = 0.001
#: recordings shorter than this many frames are searched with every fit in the space of
#: all candidates (one compilation); longer ones in a space per round. A fit in the space
#: of the 47 candidates of a 6-joint robot costs ~0.18 ms per frame more than one in its
#: own, a new space ~12 s of compilation (2-core machine); a search makes ~10 fits in ~3
#: spaces, so the two break even near 20 000 frames
SHARED_SPACE_FRAMES = 20_000

#: contiguous time blocks of the held-out check; odd and even blocks are the two folds
HELDOUT_BLOCKS = 8
#: significant candidates refitted per round, strongest score first: the score test is
#: the refit's likelihood ratio to first order, so a round whose strongest few all fail
#: the refit or the held-out check has nothing further down to name
MAX_REFITS = 5
#: ΔBIC below which the recording does not tell two candidates apart (Kass and Raftery's
#: "very strong" evidence starts at 10)
INDISTINCT_BIC = 10.0


@dataclasses.dataclass(frozen=True)
class Step:
    """One named effect: fitted `parameters` {name: (value, σ)} (SI units), the gap after
    adding it [m], and its `score` (likelihood ratio of the refit, dof, p-value, ΔBIC,
    and the held-out gaps before and after it [m]); `candidates`: the score tests of
    every candidate of the round; `term`: a dictionary term's report (variable,
    function, coefficients, words, where it acts); `replaces`: effects named before that
    it made redundant (dropped); `alternatives`: significant candidates of the round
    whose ΔBIC is within `INDISTINCT_BIC` of its own (the recording does not tell them
    apart)."""

    effect: str
    parameters: dict[str, tuple[float, float]]
    gap_after_m: float
    score: dict[str, Any]
    candidates: dict[str, dict[str, Any]]
    term: dict[str, Any] | None = None
    replaces: tuple[str, ...] = ()
    alternatives: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class DiscrepancyResult:
    """What the workflow found. `structure` lists, per variable, the residual-structure
    test after the last step (`statistic`, `dof`, `p_value`, `significant`).
    `gap_floor_m` is the gap a complete model reaches by chance with this noise and data
    (two standard errors of the gap's estimate): a final gap below it is noise.
    `rejected` lists candidates that passed the likelihood-ratio test but did not improve
    the held-out blocks by more than the floor (with their held-out gaps); `stopped` says
    why the search ended; `noise` is the recording's `NoiseModel`."""

    gap_before_m: float
    steps: list[Step]
    gap_after_m: float
    gap_floor_m: float
    unexplained: bool
    structure: dict[str, dict[str, Any]]
    localisation: dict[str, dict[str, Any]]
    noise_sigma_m: float
    calibration: Any
    gaps: list[float]
    residual_before: dict[str, tuple]
    residual_after: dict[str, tuple]
    noise: Any = None
    rejected: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    stopped: str = ""
    term_residuals: dict[str, tuple] = dataclasses.field(default_factory=dict)
    included: tuple[str, ...] = ()

    @property
    def named(self) -> list[str]:
        """The effects of the final model: those `included` from the start and those
        named, in order, without any that a later dictionary term replaced
        (`Step.replaces`)."""
        dropped = {e for s in self.steps for e in s.replaces}
        return [e for e in (*self.included, *(s.effect for s in self.steps)) if e not in dropped]

    @property
    def dropped(self) -> list[str]:
        """Effects named on the way and dropped when a later term explained them."""
        return [e for s in self.steps for e in s.replaces]

    @property
    def unexplained_where(self) -> list[str]:
        """Variables the remaining structure correlates with, strongest first."""
        sig = [
            (v["statistic"] / max(v["dof"], 1), k)
            for k, v in self.structure.items()
            if v["significant"]
        ]
        return [k for _, k in sorted(sig, reverse=True)]

    def to_json(self) -> dict[str, Any]:
        """DESIGN section 8: gap_before_m, steps, gap_after_m, unexplained (+ details)."""
        return {
            "converged": bool(self.calibration.converged),
            "convergence": self.calibration.convergence,
            "gap_before_m": self.gap_before_m,
            "steps": [
                {
                    "effect": s.effect,
                    "parameters": {
                        k: {"value": v, "sigma": e} for k, (v, e) in s.parameters.items()
                    },
                    "gap_after_m": s.gap_after_m,
                    "score": s.score,
                    **({"term": s.term} if s.term is not None else {}),
                    "replaces": list(s.replaces),
                    "alternatives": list(s.alternatives),
                }
                for s in self.steps
            ],
            "included": list(self.included),
            "named": self.named,
            "dropped": self.dropped,
            "gap_after_m": self.gap_after_m,
            "gap_floor_m": self.gap_floor_m,
            "unexplained": self.unexplained,
            "unexplained_where": self.unexplained_where,
            "noise_sigma_m": self.noise_sigma_m,
            "noise_model": None if self.noise is None else self.noise.to_dict(),
            "rejected": self.rejected,
            "stopped": self.stopped,
            "structure_after": self.structure,
            "localisation_before": self.localisation,
        }

    def figures(self, out_dir: str | Path) -> list[Path]:
        """PNGs: the gap step by step, the residual structure before and after, and the
        noise model."""
        from ..report import gap_figure, noise_figure, structure_figure

        out = Path(out_dir)
        extra = [] if self.noise is None else [noise_figure(out / "noise_model.png", self.noise)]
        if self.term_residuals:
            extra.append(
                structure_figure(
                    out / "discrepancy_terms.png",
                    {k: v[0] for k, v in self.term_residuals.items()},
                    {k: v[1] for k, v in self.term_residuals.items()},
                )
            )
        return extra + [
            gap_figure(
                out / "discrepancy_gap.png",
                [" + ".join(["nominal", *self.included]), *(s.effect for s in self.steps)],
                self.gaps,
                self.noise_sigma_m,
                self.gap_floor_m,
            ),
            structure_figure(
                out / "discrepancy_structure.png", self.residual_before, self.residual_after
            ),
        ]


# ----------------------------------------------------------------------------- structure


def _frame_variables(rec: Recording, angles: np.ndarray) -> dict[str, np.ndarray]:
    """Per-observation values `(N, M)` of the variables the disagreement is localised by."""
    from ..model import interpolate_joints

    n, m = rec.positions.shape[:2]
    out: dict[str, np.ndarray] = {"time": np.broadcast_to(rec.time[:, None], (n, m))}
    if rec.robot is not None:
        import jax.numpy as jnp

        q = np.asarray(
            interpolate_joints(
                jnp.asarray(rec.robot.time), jnp.asarray(rec.robot.joints), jnp.asarray(rec.time)
            )
        )
        for j in range(q.shape[1]):
            out[f"joint {j + 1}"] = np.broadcast_to(q[:, j, None], (n, m))
        qd = np.gradient(q, rec.time, axis=0)
        qdd = np.gradient(qd, rec.time, axis=0)
        for j in range(q.shape[1]):
            out[f"joint {j + 1} velocity"] = np.broadcast_to(qd[:, j, None], (n, m))
        out["joint speed"] = np.broadcast_to(np.linalg.norm(qd, axis=1)[:, None], (n, m))
        out["joint acceleration"] = np.broadcast_to(np.linalg.norm(qdd, axis=1)[:, None], (n, m))
    if rec.program is not None and rec.program.segment is not None:
        out["program segment"] = np.broadcast_to(rec.program.segment[:, None], (n, m))
    out["LED"] = np.broadcast_to(np.arange(m)[None, :], (n, m))
    out["emission angle"] = angles
    return out


def _structure(
    residual: np.ndarray, weight: np.ndarray, variables: dict[str, np.ndarray], bins: int = 10
) -> dict[str, dict[str, Any]]:
    """χ² test per variable of binned means of the noise-normalised residual.

    Under a complete model u = r·√w is white with unit variance per axis, so the mean of
    n values in a bin has variance 1/n and ``Σ_b n_b |ū_b|²`` is χ² with 3·bins dof.
    """
    use = np.isfinite(residual[..., 0]) & (weight > 0)
    u = residual[use] * np.sqrt(weight[use])[:, None]
    out = {}
    for name, values in variables.items():
        v = np.asarray(values)[use]
        ok = np.isfinite(v)
        if ok.sum() < 20:
            continue
        uniq = np.unique(v[ok])
        if uniq.size <= bins:
            labels = np.searchsorted(uniq, v[ok])
        else:
            edges = np.unique(np.quantile(v[ok], np.linspace(0, 1, bins + 1)))
            labels = np.clip(np.searchsorted(edges, v[ok], side="right") - 1, 0, edges.size - 2)
        k = labels.max() + 1
        cnt = np.bincount(labels, minlength=k)
        sums = np.stack([np.bincount(labels, u[ok][:, a], minlength=k) for a in range(3)], 1)
        good = cnt > 0
        stat = float(np.sum(sums[good] ** 2 / cnt[good, None]))
        dof = 3 * int(good.sum())
        out[name] = {"statistic": stat, "dof": dof, "p_value": float(stats.chi2.sf(stat, dof))}
    n_tests = max(1, len(out))
    for v in out.values():
        v["significant"] = bool(v["p_value"] < ALPHA_STRUCTURE / n_tests)
    return out


def _binned_rms(residual, variables, name, bins=20):
    """(bin centres, residual RMS [m]) of the 3-D residual against one variable."""
    use = np.isfinite(residual[..., 0])
    v = np.asarray(variables[name])[use]
    r2 = np.sum(residual[use] ** 2, -1)
    ok = np.isfinite(v)
    v, r2 = v[ok], r2[ok]
    edges = np.unique(np.quantile(v, np.linspace(0, 1, bins + 1)))
    lab = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    k = edges.size - 1
    cnt = np.bincount(lab, minlength=k)
    rms = np.sqrt(np.bincount(lab, r2, minlength=k) / np.maximum(cnt, 1))
    centre = np.bincount(lab, v, minlength=k) / np.maximum(cnt, 1)
    return centre[cnt > 0], rms[cnt > 0]


# ----------------------------------------------------------------------------- workflow


def _gap(res, var3: np.ndarray, share: float = 1.0) -> float:
    """``sqrt(max(0, mean|r|² − share · mean var3))`` [m] over the observations with a
    residual; `share` = 1 − p/n, the noise fraction a fit of p parameters leaves."""
    r = res.residuals
    use = np.isfinite(r[..., 0]) & np.isfinite(var3)
    return float(np.sqrt(max(0.0, np.mean(np.sum(r[use] ** 2, -1)) - share * np.mean(var3[use]))))


def _gap_floor(res, var3: np.ndarray, rel_se_var: float) -> float:
    """The gap a complete model reaches by chance [m]: two standard errors of
    ``mean|r|² − mean 3σ̂²`` (of the residual's mean square, and of the noise model's
    mean variance with relative standard error `rel_se_var`), under the root."""
    r = res.residuals
    use = np.isfinite(r[..., 0]) & np.isfinite(var3)
    r2 = np.sum(r[use] ** 2, -1)
    se_r = np.std(r2) / np.sqrt(r2.size)
    se_v = np.mean(var3[use]) * rel_se_var
    return float(np.sqrt(2.0 * np.hypot(se_r, se_v)))


def _share(res) -> float:
    return 1.0 - res.n_params / max(res.n_residuals, 1)


def _aligned(rec: Recording, res, values: np.ndarray) -> np.ndarray:
    """`values` `(N, M)` in the recording's LED columns, reordered to `res.led_ids`."""
    col = {int(i): k for k, i in enumerate(np.asarray(rec.led_ids))}
    return values[:, [col[int(i)] for i in res.led_ids]]


class _HeldOut:
    """Two-fold cross-validation over contiguous time blocks (odd against even): the
    gap of a model on the blocks it was not fitted to [m], over the LEDs that the
    blocks it was fitted to see (an LED seen only in the held-out blocks has no
    position the fit could determine)."""

    def __init__(self, rec: Recording, weights: np.ndarray, var: np.ndarray):
        from ..estimate.calibration import fit, predict_residuals

        self._fit, self._predict = fit, predict_residuals
        n = rec.n_frames
        self.fold = (np.arange(n) * HELDOUT_BLOCKS // n) % 2
        self.rec, self.weights, self.var3 = rec, weights, 3.0 * var

    def gap(self, estimate: tuple[str, ...], init, space: tuple[str, ...] = ()) -> float:
        r2, v3 = [], []
        for f in (0, 1):
            train = np.where((self.fold != f)[:, None], self.weights, 0.0)
            res = self._fit(
                self.rec,
                estimate=estimate,
                weights=train,
                init=init,
                space=space,
                robust_sigma=False,
            )
            d = self._predict(self.rec, res, space)[self.fold == f]
            v = _aligned(self.rec, res, self.var3)[self.fold == f]
            trained = np.any(_aligned(self.rec, res, train) > 0, axis=0)
            use = np.isfinite(d[..., 0]) & np.isfinite(v) & trained[None, :]
            r2.append(np.sum(d[use] ** 2, -1))
            v3.append(v[use])
        r2, v3 = np.concatenate(r2), np.concatenate(v3)
        return float(np.sqrt(max(0.0, np.mean(r2) - np.mean(v3))))


def _of_effect(name: str, effect: str) -> bool:
    return name == effect or name.startswith(effect + "[") or name.startswith(effect + ".")


def _effect_parameters(res, effect: str) -> dict[str, tuple[float, float]]:
    sig = res.sigma
    fixed = set(res.identifiability.get("fixed_parameters", []))
    out = {}
    for name in res.parameter_names:
        if _of_effect(name, effect):
            if name in fixed:
                continue
            out[name] = (float(_value_of(res, name)), float(sig.get(name, np.nan)))
    return out


def _value_of(res, pname: str) -> float:
    """Value of a covariance parameter name like ``joint_offset[2]``, ``link_length[1].a``
    or ``joint1_harmonic2.sin``."""
    head, _, comp = pname.partition(".")
    t = term(head)
    if t is not None:
        return float(np.asarray(res.effects[head], float)[t.components.index(comp)])
    base, _, rest = pname.partition("[")
    v = np.asarray(res.effects.get(base, 0.0), float)
    if not rest:
        return float(v)
    idx, _, comp = rest.partition("]")
    v = v[int(idx)]
    if comp.startswith("."):
        v = v[{"d": 0, "a": 1, "alpha": 0, "beta": 1, "x": 0, "y": 1, "z": 2}[comp[1:]]]
    return float(v)


def _free_count(res, effect: str) -> int:
    return len(_effect_parameters(res, effect))


def _test(value: float, dof: int, n_obs: int, **extra) -> dict[str, Any]:
    return {
        **extra,
        "dof": dof,
        "p_value": float(stats.chi2.sf(max(value, 0.0), dof)),
        "delta_bic": float(value - dof * np.log(n_obs)),
    }


def _term_block(res, effect: str) -> tuple[np.ndarray, np.ndarray]:
    """Fitted coefficients of dictionary term `effect` and their covariance (the larger of
    the Gauss–Newton and the cluster-robust one, as `CalibrationResult.sigma`)."""
    t = term(effect)
    names = [f"{effect}.{c}" for c in t.components]
    idx = [res.parameter_names.index(n) if n in res.parameter_names else -1 for n in names]
    values = np.asarray(res.effects[effect], float)
    cov = np.zeros((t.size, t.size))
    ok = [k for k, i in enumerate(idx) if i >= 0]
    if ok:
        sel = [idx[k] for k in ok]
        blocks = [np.asarray(res.covariance)[np.ix_(sel, sel)]]
        if res.covariance_robust is not None:
            blocks.append(np.asarray(res.covariance_robust)[np.ix_(sel, sel)])
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
        qj = np.asarray(q)[:, t.joint]
        where = {"variable_range": [float(qj.min()), float(qj.max())], "unit": "rad"}
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


def _term_report(
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


def _without(res, effect: str):
    """`res` with `effect` set to zero (the start of a refit that leaves it out)."""
    eff = dict(res.effects)
    eff[effect] = np.zeros_like(np.asarray(eff[effect], float)).tolist()
    return dataclasses.replace(res, effects=eff)


def _profile_motion_threshold(rec, named, current, weights, space):
    """The speed [rad/s] below which a joint counts as at rest (the deadband of a
    velocity-sign term), by profile likelihood: the model `named` refitted (from
    `current`) at thresholds a factor 2 apart from `MOTION_THRESHOLD` to 0.5 rad/s, then
    2^¼ and 2^(1/16) apart around the best (23 refits). The threshold is data
    (`motion_sign`), so the refits share one compilation. Returns (threshold, the refit
    there, the interval of thresholds within Δχ² ≤ 1 of it)."""
    from ..estimate.calibration import fit

    chi2: dict[float, float] = {}

    def refit(d: float, robust_sigma: bool = False):
        return fit(
            rec,
            estimate=tuple(named),
            weights=weights,
            init=current,
            space=space,
            robust_sigma=robust_sigma,
            motion_threshold=d,
        )

    for d in MOTION_THRESHOLD * 2.0 ** np.arange(10):
        chi2[float(d)] = refit(float(d)).chi2
    for step in (1 / 4, 1 / 16):
        centre = min(chi2, key=chi2.get)
        for d in centre * 2.0 ** (np.arange(-3, 4) * step):
            if float(d) not in chi2:
                chi2[float(d)] = refit(float(d)).chi2
    best = min(chi2, key=chi2.get)
    inside = [d for d in chi2 if chi2[d] - chi2[best] <= 1.0]
    return best, refit(best, robust_sigma=True), (min(inside), max(inside))


def _simpler_model(rec, named, current, offered, weights, n_obs, shared, nominal=None):
    """The dictionary term that alone has a lower BIC than the model `named` (fitted as
    `current`), with its refit (no cluster-robust σ), its score and the score tests from
    the nominal model (`nominal`, fitted here if None); None if no term does. The terms
    tried are the `MAX_REFITS` strongest by the score test from the nominal model,
    refitted in one space (`shared`, else their own)."""
    from ..estimate.calibration import fit, score_effects

    if nominal is None:
        nominal = fit(rec, weights=weights, space=shared or (), robust_sigma=False)
    tests = {
        c: _test(v["statistic"], v["dof"], n_obs, test="score", statistic=v["statistic"])
        for c, v in score_effects(rec, nominal, offered, weights=weights).items()
        if v["dof"] > 0
    }
    k_now = sum(_free_count(current, e) for e in named)
    bic_now = current.chi2 + k_now * np.log(n_obs)
    best = None
    top = [
        c for c in sorted(tests, key=lambda c: -tests[c]["delta_bic"]) if tests[c]["delta_bic"] > 0
    ]
    space = shared or tuple(top[:MAX_REFITS])
    for c in top[:MAX_REFITS]:
        r = fit(rec, estimate=(c,), weights=weights, init=nominal, space=space, robust_sigma=False)
        k = _free_count(r, c)
        bic = r.chi2 + k * np.log(n_obs)
        if k and bic < bic_now and (best is None or bic < best[2]):
            best = (c, r, bic, k)
    if best is None:
        return None
    c, r, bic, k = best
    lr = float(nominal.chi2 - r.chi2)
    score = _test(
        lr, k, n_obs, likelihood_ratio=lr, delta_bic_against_replaced=float(bic_now - bic)
    )
    return c, r, score, tests, space


def discover(
    rec: Recording,
    *,
    candidates: tuple[str, ...] | None = None,
    max_steps: int = 4,
    progress=None,
    include: tuple[str, ...] = (),
) -> DiscrepancyResult:
    """Run the discrepancy workflow on `rec` (needs a robot log and a tool).

    `candidates`: effect names to try (default: the library of DESIGN section 7,
    `robtraj.model.LIBRARY`, and the dictionary's terms for the robot,
    `robtraj.model.dictionary`, searched together). `include`: effects the model has
    from the start (fitted in the nominal fit, e.g. a calibration's set); a named term
    may replace them like the effects named before it.
    While the gap exceeds its floor, each round scores every remaining candidate at once
    with Rao's score test (`robtraj.estimate.calibration.score_effects`: one pass over
    the recording, one compilation); the significant ones are refitted in order of their
    ΔBIC, and the first whose refit confirms it by the likelihood-ratio test and lowers
    the held-out gap (two folds of alternate time blocks) by more than the floor is
    named. When a dictionary term is named, each effect named before it is tested again
    next to it (likelihood ratio and held-out gap, as when it was named); those it has
    made redundant are dropped (`Step.replaces`): one term that explains the structure
    is preferred to the library effects that stood in for it. The search stops when the
    gap is within its floor, when no candidate qualifies, or when no structure is left
    against any variable. Then, if library effects were named, the dictionary terms are
    tried alone: one with a lower BIC than the whole named model, and a held-out gap
    no worse by more than the floor, replaces it (a last step whose `replaces` lists
    them).
    """
    from ..estimate import clock_effects
    from ..estimate.calibration import fit, library_space, score_effects

    say = progress or (lambda _msg: None)
    if candidates is None:
        n_joints = 6 if rec.robot is None else int(np.shape(rec.robot.joints)[1])
        candidates = (*LIBRARY, *dictionary(n_joints))
    include = tuple(dict.fromkeys((*clock_effects(rec.robot), *include)))
    candidates = tuple(c for c in candidates if c not in include)
    bad = [c for c in (*candidates, *include) if not is_effect(c)]
    if bad:
        raise UserError(
            f"unknown effect(s) {', '.join(bad)} (known: the library {', '.join(LIBRARY)}, "
            "link_twist and the dictionary's terms, robtraj.model.dictionary)"
        )
    say("emission angles and the noise model of the recording")
    angles = observation_angles(rec)
    noise_model, var = observation_noise(rec, angles)
    weights = np.where(rec.visible & np.isfinite(var), 1.0 / var, 0.0)
    noise = float(np.sqrt(np.nanmean(var)))
    variables = _frame_variables(rec, angles)

    say("nominal fit")
    # fits share a space (one compilation): that of every candidate on short recordings,
    # else per round that of the named effects and the candidates it may refit
    shared = library_space(candidates, include) if rec.n_frames < SHARED_SPACE_FRAMES else None
    # search fits leave out the cluster-robust σ (a pass and a compilation of their own);
    # the fit a step reports is refitted with it (`reported`)
    current = fit(rec, estimate=include, weights=weights, space=shared or (), robust_sigma=False)
    nominal_fit, fitted_in, robust = current, shared or (), False

    def reported(res, estimate, space):
        return fit(rec, estimate=tuple(estimate), weights=weights, init=res, space=space)

    var3 = _aligned(rec, current, 3.0 * var)
    weights_c = _aligned(rec, current, weights)
    n_obs = int(np.isfinite(current.residuals[..., 0]).sum()) * 3
    gap0 = _gap(current, var3, _share(current))
    gaps = [gap0]
    localisation = _structure(current.residuals, weights_c, variables)
    before = {
        k: _binned_rms(current.residuals, variables, k)
        for k in ("time", "joint 2", "emission angle")
        if k in variables
    }
    nominal_residuals = current.residuals

    def floor_of(res) -> float:
        return _gap_floor(res, var3, noise_model.level_rel_se)

    floor = floor_of(current)
    heldout = _HeldOut(rec, weights, var)
    heldout_gap: float | None = None
    steps: list[Step] = []
    rejected: list[dict[str, Any]] = []
    named: list[str] = list(include)
    tried: set[str] = set()
    stopped = "max_steps"
    for _ in range(max_steps):
        if gaps[-1] <= floor:
            stopped = "gap_within_floor"
            break
        remaining = [c for c in candidates if c not in named and c not in tried]
        if not remaining:
            stopped = "no_candidates"
            break
        say(f"score test of {len(remaining)} candidate effects")
        alpha = ALPHA / len(remaining)
        scores = {
            c: _test(v["statistic"], v["dof"], n_obs, test="score", statistic=v["statistic"])
            for c, v in score_effects(rec, current, remaining, weights=weights).items()
            if v["dof"] > 0
        }
        significant = [
            c
            for c in sorted(scores, key=lambda c: -scores[c]["delta_bic"])
            if scores[c]["p_value"] < alpha and scores[c]["delta_bic"] > 0
        ]
        accepted = None
        space = shared or tuple(dict.fromkeys((*named, *significant[:MAX_REFITS])))
        for cand in significant[:MAX_REFITS]:
            say(f"refitting with {cand}")
            r = fit(
                rec,
                estimate=(*named, cand),
                weights=weights,
                init=current,
                space=space,
                robust_sigma=False,
            )
            k = _free_count(r, cand)
            if k == 0:
                continue
            lr = float(current.chi2 - r.chi2)
            score = _test(lr, k, n_obs, likelihood_ratio=lr)
            if not (score["p_value"] < alpha and score["delta_bic"] > 0):
                continue
            say(f"held-out check of {cand}")
            if heldout_gap is None:
                heldout_gap = heldout.gap(tuple(named), current, fitted_in)
            after = heldout.gap((*named, cand), r, space)
            score.update(heldout_gap_before_m=heldout_gap, heldout_gap_after_m=after)
            if heldout_gap - after > floor:
                accepted = (cand, r, score)
                heldout_gap = after
                break
            rejected.append({"effect": cand, **score})
        if accepted is None:
            stopped = "nothing_qualifies"
            break
        best, current, score = accepted
        fitted_in, robust = space, False
        interval = None
        if term(best) is not None and term(best).motion:
            say(f"deadband of {best}: profile of the motion threshold")
            _, current, interval = _profile_motion_threshold(
                rec, named + [best], current, weights, space
            )
            robust = True
            heldout_gap = heldout.gap((*named, best), current, space)
            score.update(heldout_gap_after_m=heldout_gap)
        # candidates the score test cannot tell from the named one
        alternatives = tuple(
            c
            for c in significant
            if c != best and scores[best]["delta_bic"] - scores[c]["delta_bic"] < INDISTINCT_BIC
        )
        named.append(best)
        replaces: list[str] = []
        if term(best) is not None:
            for old in [n for n in named if n != best]:
                keep = [n for n in named if n != old]
                say(f"is {old} still needed next to {best}?")
                r = fit(
                    rec,
                    estimate=tuple(keep),
                    weights=weights,
                    init=_without(current, old),
                    space=space,
                    robust_sigma=False,
                )
                k = _free_count(current, old)
                lr = float(r.chi2 - current.chi2)
                test = _test(lr, max(k, 1), n_obs)
                needed = test["p_value"] < ALPHA / max(len(candidates), 1) and test["delta_bic"] > 0
                if needed:
                    h = heldout.gap(tuple(keep), r, space)
                    needed = h - heldout_gap > floor
                if not needed:
                    replaces.append(old)
                    named.remove(old)
                    tried.add(old)
                    current, robust = r, False
                    heldout_gap = heldout.gap(tuple(named), current, space)
        if not robust:
            current, robust = reported(current, named, space), True
        gaps.append(_gap(current, var3, _share(current)))
        floor = floor_of(current)
        steps.append(
            Step(
                best,
                _effect_parameters(current, best),
                gaps[-1],
                score,
                scores,
                _term_report(rec, current, best, angles, interval),
                tuple(replaces),
                alternatives,
            )
        )
        say(f"named {best}: gap {gaps[-2] * 1e6:.1f} → {gaps[-1] * 1e6:.1f} µm")
        if replaces:
            say(f"{best} replaces {', '.join(replaces)}")
        # nothing structured left against any variable: no further effect can stand out
        if not any(
            v["significant"] for v in _structure(current.residuals, weights_c, variables).values()
        ):
            stopped = "no_structure"
            break
    else:
        if gaps[-1] <= floor:
            stopped = "gap_within_floor"
    # a simpler model: one dictionary term alone in place of what was named
    offered = [c for c in candidates if term(c) is not None and c not in named]
    if offered and any(term(n) is None for n in named):
        say(f"is one dictionary term a simpler model than {', '.join(named)}?")
        swap = _simpler_model(
            rec,
            named,
            current,
            offered,
            weights,
            n_obs,
            shared,
            nominal=None if include else nominal_fit,
        )
        if swap is not None:
            c, r, score, tests, swap_space = swap
            if heldout_gap is None:
                heldout_gap = heldout.gap(tuple(named), current, fitted_in)
            h = heldout.gap((c,), r, swap_space)
            score.update(heldout_gap_before_m=heldout_gap, heldout_gap_after_m=h)
            if h <= heldout_gap + floor:
                say(f"{c} alone replaces {', '.join(named)}")
                replaced, named, heldout_gap = tuple(named), [c], h
                current, fitted_in = reported(r, named, swap_space), swap_space
                gaps.append(_gap(current, var3, _share(current)))
                floor = floor_of(current)
                steps.append(
                    Step(
                        c,
                        _effect_parameters(current, c),
                        gaps[-1],
                        score,
                        tests,
                        _term_report(rec, current, c, angles),
                        replaced,
                    )
                )
            else:
                rejected.append({"effect": c, **score})
    if not robust:
        current = reported(current, named, fitted_in)
    structure = _structure(current.residuals, weights_c, variables)
    after = {k: _binned_rms(current.residuals, variables, k) for k in before}
    unexplained = gaps[-1] > floor and any(v["significant"] for v in structure.values())
    term_residuals = {}
    for name in named:
        t = term(name)
        if t is not None and t.frame_variable in variables:
            v = t.frame_variable
            term_residuals[v] = (
                _binned_rms(nominal_residuals, variables, v),
                _binned_rms(current.residuals, variables, v),
            )
    return DiscrepancyResult(
        gap_before_m=gap0,
        steps=steps,
        gap_after_m=gaps[-1],
        gap_floor_m=floor,
        unexplained=unexplained,
        structure=structure,
        localisation=localisation,
        noise_sigma_m=noise,
        calibration=current,
        gaps=gaps,
        residual_before=before,
        residual_after=after,
        noise=noise_model,
        rejected=rejected,
        stopped=stopped,
        term_residuals=term_residuals,
        included=include,
    )
