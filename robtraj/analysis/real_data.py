"""Real measured data: calibrate a UR10 from laser-tracker pose measurements and find
the effects its nominal model misses, validated across measurement series.

Data: the ``ipa-robot-accuracy`` data set, path given by the caller (UR10 + Leica laser tracker with a T-Mac
6-DOF probe; static poses, one measured probe pose each). See ``docs/real_ur10.md``.

Measurement model (DESIGN section 5 at pose level, through the one forward model of
`robtraj.model`)::

    camera_from_probe_i = camera_from_base(T_i) · flange_pose(q_i; effects) · flange_from_probe

with ``camera_from_base(T)`` translated by ``thermal_drift · (T − T̄)`` and positions
scaled by ``1 + tracker_scale``. The residual of pose i is 6-D: the probe-origin
position error [m] in the tracker frame and the rotation vector of
``measured⁻¹ · predicted`` [rad]. Each pose is one observation — the 4 virtual points
of the importer carry exactly this information; working with poses avoids a free
"constellation" that the bundle calibration (`robtraj.estimate.calibration.fit`)
would otherwise estimate for points that are exact by construction.

Parameters: a tangent-space correction of camera←base (6) and flange←probe (6) around
a closed-form start (Shah's robot-world/hand-eye solution), and the `Effects` fields
``joint_offset`` (6), ``link_length`` (6×2 ``[Δd, Δa]``), ``link_twist`` (6×2
``[Δα, Δβ]``), ``joint_compliance`` (6),
``thermal_drift`` (3) and ``tracker_scale`` (1), solved by the package's one engine
(`robtraj.estimate.solve`). Identifiability (`robtraj.estimate.identifiability`): null
directions of the column-scaled normal matrix name the parameters that cannot be told
apart from the rigid transforms or from each other; those effect parameters are fixed
at zero and reported (never the rigid transforms).

Weights: per block (position, rotation) the variance is ``std_i² + s²`` where
``std_i`` is the tracker's own standard deviation of pose i (Series B; zero where the
file has none) and ``s²`` the unexplained variance of the block estimated from the
nominal fit's residuals: the residual is ~35× the tracker scatter per axis (model
error, not noise), and Series A has no std. (On Series B, pure ``1/std²`` weights
predict Series A about as well; see ``docs/real_ur10.md``.)

Cross-series prediction: effects fitted on one series are frozen and only the rigid
transforms (camera←base and flange←probe, or camera←base alone) are refitted on the
other series; its error is what the model predicts for data it never saw.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ._pose_fit import (
    HARMONIC_TERMS,
    PoseFit,
    cross_predict,
    error_summary,
    fit_poses,
    parameter_names,
    parse_effect_spec,
    pose_errors,
    tracker_noise,
)
from ._pose_series import PoseSeries, load_series, series_from_recording

__all__ = [
    "CANDIDATES",
    "CrossSeries",
    "PoseFit",
    "PoseSeries",
    "Workflow",
    "cross_predict",
    "error_summary",
    "fit_poses",
    "load_series",
    "parameter_names",
    "parse_effect_spec",
    "pose_errors",
    "run_workflow",
    "series_from_recording",
    "tracker_noise",
]

#: effects tried by the discrepancy workflow on pose data (geometric, then non-geometric)
#: (``joint_compliance[1,2]``: only shoulder and elbow, the joints carrying the arm's
#: weight; the wrist joints see gravity torques of a few N·m, so their compliance is
#: poorly determined and fits whatever else is left)
CANDIDATES = (
    "joint_offset",
    "link_length",
    "link_twist",
    "joint_compliance",
    "joint_compliance[1,2]",
    "thermal_drift",
)
#: the kinematic calibration: the full geometric error set (DH lengths, twists and
#: Hayati's tilt of parallel axes, zero offsets), its degeneracies fixed by identifiability
CALIBRATION = ("joint_offset", "link_length", "link_twist")
#: the dictionary's terms the pose fit takes: every joint's angle harmonics
#: (`robtraj.model.dictionary`; ``run_workflow(candidates=CANDIDATES + DICTIONARY)``)
DICTIONARY = HARMONIC_TERMS
#: smallest relative improvement of the cross-series error that counts
MIN_CROSS_GAIN = 0.02

# ----------------------------------------------------------------------------- workflow


@dataclasses.dataclass(frozen=True)
class CrossSeries:
    """One model (set of effects) fitted on each series and predicting the other."""

    effects: tuple[str, ...]
    fitted: dict[str, PoseFit]
    cross: dict[str, PoseFit]  # key "A->B": fitted on A, predicting B

    def row(self, noise: dict[str, float]) -> dict[str, dict[str, float]]:
        out = {f"fit {k}": v.summary(noise[k]) for k, v in self.fitted.items()}
        out.update({k: v.summary(noise[k[-1]]) for k, v in self.cross.items()})
        return out


def evaluate(
    effects: Sequence[str],
    series: dict[str, PoseSeries],
    rigid: Sequence[str] = ("camera", "probe"),
    block_sigma: dict[str, tuple[float, float]] | None = None,
) -> CrossSeries:
    """Fit `effects` on every series and predict each other series from it."""
    fitted = {
        k: fit_poses(
            s, estimate=effects, block_sigma=None if block_sigma is None else block_sigma[k]
        )
        for k, s in series.items()
    }
    cross = {}
    for a in series:
        for b in series:
            if a != b:
                cross[f"{a}->{b}"] = fit_poses(
                    series[b],
                    fixed=fitted[a],
                    rigid=rigid,
                    block_sigma=None if block_sigma is None else block_sigma[b],
                )
    return CrossSeries(tuple(effects), fitted, cross)


def _bic(before: PoseFit, after: PoseFit) -> dict[str, Any]:
    """Likelihood ratio with the noise scale profiled out (σ² estimated from the data)
    and ΔBIC = LR − Δk·ln n (positive: the effect is supported)."""
    from scipy import stats

    n = after.n_residuals
    k = after.n_free - before.n_free
    lr = n * math.log(max(before.chi2, 1e-300) / max(after.chi2, 1e-300))
    return {
        "likelihood_ratio": lr,
        "dof": k,
        "p_value": float(stats.chi2.sf(max(lr, 0.0), max(k, 1))),
        "delta_bic": lr - k * math.log(n),
    }


def _cross_cost(cs: CrossSeries) -> dict[str, tuple[float, float]]:
    """Cross-series error per direction: position RMS [m] and angle RMS [rad]."""
    return {
        k: (
            float(np.sqrt(np.mean(v.position_error**2))),
            float(np.sqrt(np.mean(v.angle_error**2))),
        )
        for k, v in cs.cross.items()
    }


@dataclasses.dataclass(frozen=True)
class Workflow:
    """The discrepancy workflow on pose data, validated across series.

    `steps`: one dict per named effect (``effect``, ``fitted`` and ``cross`` summaries,
    per-series ``score`` and ``parameters``); `rejected`: candidates that improved
    the fitted series (ΔBIC > 0) but not the cross-series prediction (over-fitting),
    with the round they were tried in; `models`: the CrossSeries after each step
    (index 0: nominal rigid); `calibration`: the kinematic calibration of item 1.
    """

    series: tuple[str, ...]
    rigid: tuple[str, ...]
    noise_m: dict[str, float]
    models: list[CrossSeries]
    steps: list[dict[str, Any]]
    rejected: list[dict[str, Any]]
    candidates_tried: list[dict[str, Any]]
    calibration: CrossSeries

    @property
    def named(self) -> list[str]:
        return [s["effect"] for s in self.steps]

    def table(self) -> list[dict[str, Any]]:
        """Rows (model, column, figures) for the report table."""
        rows = []
        labels = ["nominal rigid"] + [f"+ {e}" for e in self.named]
        for label, m in zip(labels, self.models):
            for col, vals in m.row(self.noise_m).items():
                rows.append({"model": label, "column": col, **vals})
        for col, vals in self.calibration.row(self.noise_m).items():
            rows.append(
                {
                    "model": "calibration (" + " + ".join(self.calibration.effects) + ")",
                    "column": col,
                    **vals,
                }
            )
        return rows

    def markdown(self) -> str:
        """The report table: mean / max position [mm], orientation [deg], gap [mm]."""
        return rows_markdown(self.table())

    def to_json(self) -> dict[str, Any]:
        """Named effects with their parameters per series, the rejected candidates, every
        candidate's scores, the calibration and the report table (JSON-able)."""
        return {
            "series": list(self.series),
            "rigid_refitted": list(self.rigid),
            "noise_m": self.noise_m,
            "named": self.named,
            "steps": [
                {
                    "round": s["round"],
                    "effect": s["effect"],
                    "delta_bic": {k: v["delta_bic"] for k, v in s["score"].items()},
                    "cross_gain": s["cross_gain"],
                    "parameters": {
                        k: {n: list(vs) for n, vs in ps.items()}
                        for k, ps in s["parameters"].items()
                    },
                }
                for s in self.steps
            ],
            "rejected": [{"round": e["round"], "effect": e["effect"]} for e in self.rejected],
            "candidates": [
                {k: v for k, v in e.items() if k != "score"}
                | {"delta_bic": {s: v["delta_bic"] for s, v in e["score"].items()}}
                for e in self.candidates_tried
            ],
            "calibration_parameters": {
                k: {n: list(vs) for n, vs in f.parameters().items()}
                for k, f in self.calibration.fitted.items()
            },
            "fixed_unidentifiable": {
                k: f.identifiability["dropped"] for k, f in self.calibration.fitted.items()
            },
            "table": self.table(),
        }


def _relative_gain(before: dict, after: dict, which: int | None = None) -> dict[str, float]:
    """Relative decrease of the cross-series error per direction: of the position RMS
    (`which=0`), the angle RMS (`which=1`) or, by default, the mean of the two."""
    out = {}
    for k in before:
        g = [(before[k][i] - after[k][i]) / before[k][i] for i in (0, 1)]
        out[k] = float(0.5 * (g[0] + g[1]) if which is None else g[which])
    return out


def _group(spec: str) -> str:
    """What naming `spec` takes out of the candidates: its effect (all of
    ``joint_compliance`` with ``joint_compliance[1,2]``), or the term itself."""
    return spec if spec in HARMONIC_TERMS else parse_effect_spec(spec)[0]


def run_workflow(
    series: dict[str, PoseSeries],
    *,
    candidates: Sequence[str] = CANDIDATES,
    rigid: Sequence[str] = ("camera", "probe"),
    max_steps: int = 4,
    min_cross_gain: float = MIN_CROSS_GAIN,
    progress: Callable[[str], None] | None = None,
) -> Workflow:
    """Greedy discrepancy workflow with cross-series validation.

    Start: the nominal rigid model (only camera←base and flange←probe fitted). Each
    round fits every remaining candidate added to the named ones on every series and
    scores it (a) on the fitted series by a likelihood ratio with σ profiled and ΔBIC,
    and (b) by the cross-series prediction: effects frozen, the `rigid` transforms
    refitted on the other series. A candidate is eligible only if ΔBIC > 0 on every
    fitted series **and** the cross-series cost (mean relative decrease of position
    and orientation RMS) falls by at least `min_cross_gain` in every direction; the
    eligible one with the largest summed ΔBIC is named. A candidate with ΔBIC > 0 that
    fails (b) is recorded in `rejected` as over-fitting. Stops when none is eligible.
    """
    say = progress or (lambda _m: None)
    noise = {k: tracker_noise(s) for k, s in series.items()}
    nz = [v for v in noise.values() if v > 0]
    if nz:  # same tracker: a series without reported std gets the others' noise level
        noise = {k: (v if v > 0 else float(np.mean(nz))) for k, v in noise.items()}
    say("nominal rigid fit")
    current = evaluate((), series, rigid)
    bsig = {k: v.block_sigma for k, v in current.fitted.items()}
    models = [current]
    named: list[str] = []
    steps: list[dict[str, Any]] = []
    rejected: list[dict[str, Any]] = []
    tried: list[dict[str, Any]] = []
    for rnd in range(max_steps):
        taken = {_group(c) for c in named}
        remaining = [c for c in candidates if _group(c) not in taken]
        if not remaining:
            break
        base_cross = _cross_cost(current)
        scored = {}
        for cand in remaining:
            say(f"round {rnd + 1}: trying {cand}")
            cs = evaluate((*named, cand), series, rigid, bsig)
            score = {k: _bic(current.fitted[k], cs.fitted[k]) for k in series}
            gain = _relative_gain(base_cross, _cross_cost(cs))
            fits_better = all(s["delta_bic"] > 0 for s in score.values())
            predicts_better = all(g >= min_cross_gain for g in gain.values())
            entry = {
                "round": rnd + 1,
                "effect": cand,
                "score": score,
                "cross_gain": gain,
                "cross_gain_position": _relative_gain(base_cross, _cross_cost(cs), which=0),
                "cross_gain_angle": _relative_gain(base_cross, _cross_cost(cs), which=1),
                "fits_better": fits_better,
                "predicts_better": predicts_better,
            }
            tried.append(entry)
            scored[cand] = (cs, entry)
        eligible = {
            c: v for c, v in scored.items() if v[1]["fits_better"] and v[1]["predicts_better"]
        }
        for c, (_, entry) in scored.items():
            if entry["fits_better"] and not entry["predicts_better"] and c not in eligible:
                rejected.append(entry)
        if not eligible:
            break
        best = max(
            eligible, key=lambda c: sum(s["delta_bic"] for s in eligible[c][1]["score"].values())
        )
        current, entry = eligible[best]
        named.append(best)
        models.append(current)
        steps.append(
            {
                **entry,
                "parameters": {k: f.parameters() for k, f in current.fitted.items()},
                "fixed_unidentifiable": {
                    k: [d["parameter"] for d in f.identifiability["dropped"]]
                    for k, f in current.fitted.items()
                },
                "summary": current.row(noise),
            }
        )
        say(f"named {best}")
    say("kinematic calibration")
    calib = evaluate(CALIBRATION, series, rigid, bsig)
    return Workflow(
        series=tuple(series),
        rigid=tuple(rigid),
        noise_m=noise,
        models=models,
        steps=steps,
        rejected=rejected,
        candidates_tried=tried,
        calibration=calib,
    )


# ----------------------------------------------------------------------------- helpers


def transform_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation [m] and single rotation angle [rad] between two ``wxyz_xyz`` poses."""
    pos, ang = pose_errors(np.asarray(a)[None], np.asarray(b)[None])
    return float(pos[0]), float(ang[0])


def rigid_variants(model: CrossSeries, series: dict[str, PoseSeries]) -> dict[str, dict]:
    """Cross-series prediction with only camera←base refitted (flange←probe carried over
    from the fitting series) next to the default (camera←base and flange←probe refitted):
    ``{direction: {"camera": PoseFit, "camera+probe": PoseFit}}``."""
    out = {}
    for key, fit in model.cross.items():
        src, dst = key.split("->")
        only = fit_poses(
            series[dst],
            fixed=model.fitted[src],
            rigid=("camera",),
            block_sigma=fit.block_sigma,
        )
        out[key] = {"camera": only, "camera+probe": fit}
    return out


def rows_markdown(rows: list[dict[str, Any]]) -> str:
    """A markdown table of `Workflow.table()`-style rows."""
    head = (
        "| model | evaluated on | pos mean [mm] | pos max [mm] | ang mean [deg] "
        "| ang max [deg] | gap [mm] |\n|---|---|---|---|---|---|---|\n"
    )
    return head + "".join(
        f"| {r['model']} | {r['column']} | {r['pos_mean_mm']:.3f} | {r['pos_max_mm']:.3f} "
        f"| {r['ang_mean_deg']:.4f} | {r['ang_max_deg']:.4f} | {r['gap_mm']:.3f} |\n"
        for r in rows
    )
