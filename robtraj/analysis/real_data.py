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
``thermal_drift`` (3) and ``tracker_scale`` (1), the dictionary's joint harmonics and
the joint angle error maps (``joint{j}_map``, 256 knots each under a Gaussian
smoothness prior), solved by the package's one engine (`robtraj.estimate.solve`). Identifiability (`robtraj.estimate.identifiability`): null
directions of the column-scaled normal matrix name the parameters that cannot be told
apart from the rigid transforms or from each other; those effect parameters are fixed
at zero and reported (never the rigid transforms).

Weights: per block (position, rotation) the variance is ``std_i² + s²`` where
``std_i`` is the tracker's own standard deviation of pose i (Series B; zero where the
file has none) and ``s²`` the unexplained variance of the block estimated from the
nominal fit's residuals: the residual is ~35× the tracker scatter per axis (model
error, not noise), and Series A has no std. (On Series B, pure ``1/std²`` weights
predict Series A about as well; see ``docs/real_ur10.md``.)

Naming (`run_workflow`): on each series on its own, effects are named by blocked
cross-validation inside that series (`_pose_selection`: regions of joint space left out
one at a time); the maps' prior hyper-parameters are chosen the same way.

Cross-series prediction: effects fitted on one series are frozen and only the rigid
transforms (camera←base and flange←probe, or camera←base alone) are refitted on the
other series; its error is what the model predicts for data it never saw. The workflow
reports it as out-of-sample validation of what each series named: the other series
never takes part in the naming.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from .._blas import serial_blas
from ..model import MAP_PRIOR_GRID, map_words
from ._named_model import pose_calibration
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
    uses_maps,
)
from ._pose_selection import MIN_CV_GAIN, Selection, select
from ._pose_series import PoseSeries, load_series, series_from_recording

__all__ = [
    "CANDIDATES",
    "CrossSeries",
    "MIN_CV_GAIN",
    "PoseFit",
    "PoseSeries",
    "Selection",
    "Workflow",
    "cross_predict",
    "error_summary",
    "fit_poses",
    "load_series",
    "map_report",
    "parameter_names",
    "parse_effect_spec",
    "pose_errors",
    "run_workflow",
    "series_from_recording",
    "tracker_noise",
]

#: effects tried by the discrepancy workflow on pose data (geometric, non-geometric, and
#: every joint's angle error map as one candidate, ``joint_map``)
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
    "joint_map",
)
#: the kinematic calibration: the full geometric error set (DH lengths, twists and
#: Hayati's tilt of parallel axes, zero offsets), its degeneracies fixed by identifiability
CALIBRATION = ("joint_offset", "link_length", "link_twist")
#: the dictionary's joint harmonics the pose fit takes, as candidates
#: (``run_workflow(candidates=CANDIDATES + DICTIONARY)``)
DICTIONARY = HARMONIC_TERMS

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


@serial_blas
def evaluate(
    effects: Sequence[str],
    series: dict[str, PoseSeries],
    rigid: Sequence[str] = ("camera", "probe"),
    block_sigma: dict[str, tuple[float, float]] | None = None,
    map_prior: dict[str, tuple[float, float]] | None = None,
    maps_layout: bool = False,
) -> CrossSeries:
    """Fit `effects` on every series and predict each other series from it
    (`maps_layout`: as `fit_poses`)."""
    fitted = _each(
        lambda k: fit_poses(
            series[k],
            estimate=effects,
            block_sigma=None if block_sigma is None else block_sigma[k],
            map_prior=None if map_prior is None else map_prior.get(k),
            maps_layout=maps_layout,
        ),
        series,
    )
    pairs = [f"{a}->{b}" for a in series for b in series if a != b]

    def predict(pair: str) -> PoseFit:
        a, b = pair.split("->")
        return fit_poses(
            series[b],
            fixed=fitted[a],
            rigid=rigid,
            block_sigma=None if block_sigma is None else block_sigma[b],
        )

    return CrossSeries(tuple(effects), fitted, _each(predict, pairs))


def _each(fn: Callable[[str], Any], keys: Iterable[str]) -> dict[str, Any]:
    """``{k: fn(k)}`` over `keys` (series names), computed concurrently
    (`_concurrently`)."""
    return _concurrently({k: functools.partial(fn, k) for k in keys})


def _concurrently(tasks: dict[str, Callable[[], Any]]) -> dict[str, Any]:
    """``{k: task()}``, the tasks run in their order on up to one thread per core: the
    series are independent, and a fit's Python, NumPy and XLA compilation keep one core
    busy at a time for long stretches."""
    workers = max(1, min(len(tasks), os.cpu_count() or 1))
    if workers == 1:
        return {k: t() for k, t in tasks.items()}
    with ThreadPoolExecutor(workers) as pool:
        futures = {k: pool.submit(t) for k, t in tasks.items()}
        return {k: f.result() for k, f in futures.items()}


def _rms(fit: PoseFit) -> tuple[float, float]:
    """Position RMS [m] and angle RMS [rad] of a fit's or a prediction's errors."""
    return (
        float(np.sqrt(np.mean(fit.position_error**2))),
        float(np.sqrt(np.mean(fit.angle_error**2))),
    )


def cross_gain(before: PoseFit, after: PoseFit) -> float:
    """Relative decrease of a prediction's error from `before` to `after`: the mean of
    those of the position RMS and the angle RMS (negative: worse)."""
    (p0, a0), (p1, a1) = _rms(before), _rms(after)
    return float(0.5 * ((p0 - p1) / p0 + (a0 - a1) / a0))


def _ranges(series: PoseSeries) -> list[tuple[float, float]]:
    return [(float(lo), float(hi)) for lo, hi in zip(series.joints.min(0), series.joints.max(0))]


def map_report(fit: PoseFit, series: PoseSeries) -> dict[str, Any]:
    """A fit's joint angle error maps in words and numbers, each over the angles where
    `series` (the fitted series) has data: ``{"words": [...], "maps": {joint: {"range_rad",
    "knots_rad", "value_rad", "sigma_rad"}}, "prior": {"sigma_f_rad",
    "length_scale_rad"}}`` (the knots inside the range; empty without maps)."""
    maps = fit.maps()
    if not maps:
        return {}
    ranges = _ranges(series)
    out: dict[str, Any] = {"words": [], "maps": {}}
    for j, m in maps.items():
        lo, hi = ranges[j - 1]
        out["words"].append(map_words(j, m["value"], (lo, hi)))
        k = m["knots"]
        inside = np.mod(k - lo, 2 * np.pi) <= hi - lo
        turn = lo + np.mod(k - lo, 2 * np.pi)  # the knot's angle inside the range
        order = np.argsort(turn[inside])
        out["maps"][j] = {
            "range_rad": [lo, hi],
            "knots_rad": turn[inside][order].tolist(),
            "value_rad": m["value"][inside][order].tolist(),
            "sigma_rad": m["sigma"][inside][order].tolist(),
        }
    if fit.map_prior is not None:
        out["prior"] = {"sigma_f_rad": fit.map_prior[0], "length_scale_rad": fit.map_prior[1]}
    return out


@dataclasses.dataclass(frozen=True)
class Workflow:
    """The discrepancy workflow on pose data: effects named on each series by blocked
    cross-validation inside it, validated on the other series.

    `selections`: per training series, its `Selection` (named steps, every candidate's
    scores, the rejected over-fitting ones, the fits after each step); `cross`: per
    training series, per step (0: nominal), the prediction of each other series with the
    effects frozen and the `rigid` transforms refitted; `calibration`: the kinematic
    calibration (`CALIBRATION`) on every series, predicting the others.
    """

    series: tuple[str, ...]
    rigid: tuple[str, ...]
    noise_m: dict[str, float]
    selections: dict[str, Selection]
    cross: dict[str, list[dict[str, PoseFit]]]
    calibration: CrossSeries
    data: dict[str, PoseSeries] = dataclasses.field(repr=False, default_factory=dict)

    @property
    def named(self) -> dict[str, list[str]]:
        """The effects named on each series, in order."""
        return {k: v.named for k, v in self.selections.items()}

    @property
    def nominal(self) -> CrossSeries:
        """The nominal rigid model (only the rigid transforms fitted)."""
        return CrossSeries((), self._fits(0), self._cross(0))

    @property
    def final(self) -> CrossSeries:
        """Each series' named model and its predictions of the others."""
        return CrossSeries((), self._fits(-1), self._cross(-1))

    def _fits(self, k: int) -> dict[str, PoseFit]:
        return {s: sel.fits[k] for s, sel in self.selections.items()}

    def _cross(self, k: int) -> dict[str, PoseFit]:
        return {f"{s}->{t}": f for s, c in self.cross.items() for t, f in c[k].items()}

    @property
    def steps(self) -> list[dict[str, Any]]:
        """Every named step, with its training series (``series``), its fitted and
        cross-series figures (``fitted``, ``cross``: error summaries) and the cross-series
        gain it made (``cross_gain``: reported, not used to name)."""
        out = []
        for s, sel in self.selections.items():
            for k, st in enumerate(sel.steps, start=1):
                fit = sel.fits[k]
                cross = self.cross[s][k]
                out.append(
                    {
                        "series": s,
                        **st,
                        "fitted": fit.summary(self.noise_m[s]),
                        "cross": {
                            f"{s}->{t}": f.summary(self.noise_m[t]) for t, f in cross.items()
                        },
                        "cross_gain": {
                            f"{s}->{t}": cross_gain(self.cross[s][k - 1][t], f)
                            for t, f in cross.items()
                        },
                        "parameters": fit.parameters(),
                        "fixed_unidentifiable": [
                            d["parameter"] for d in fit.identifiability["dropped"]
                        ],
                        **({"term": _term(fit, self.data[s])} if fit.maps() else {}),
                    }
                )
        return out

    @property
    def rejected(self) -> list[dict[str, Any]]:
        return [{"series": s, **e} for s, sel in self.selections.items() for e in sel.rejected]

    @property
    def candidates_tried(self) -> list[dict[str, Any]]:
        return [{"series": s, **e} for s, sel in self.selections.items() for e in sel.candidates]

    def table(self) -> list[dict[str, Any]]:
        """Rows (model, column, figures) for the report table: per training series the
        nominal rigid model and each named step, fitted and predicting the others; then
        the calibration."""
        rows = []
        for s, sel in self.selections.items():
            labels = ["nominal rigid"] + [f"+ {e} (named on {s})" for e in sel.named]
            for k, label in enumerate(labels):
                rows.append(
                    {"model": label, "column": f"fit {s}", **sel.fits[k].summary(self.noise_m[s])}
                )
                for t, f in self.cross[s][k].items():
                    rows.append(
                        {"model": label, "column": f"{s}->{t}", **f.summary(self.noise_m[t])}
                    )
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

    def calibration_of(self, key: str, rec, source: str):
        """Series `key`'s final named model as a calibration (`CalibrationResult`), `rec`
        the recording the series was read from and `source` its path."""
        return pose_calibration(
            self.selections[key].fits[-1],
            rec,
            self.data[key],
            named=self.named[key],
            noise_m=self.noise_m[key],
            source=source,
        )

    def to_json(self) -> dict[str, Any]:
        """Named effects per series with their parameters, cross-validation and
        cross-series figures, the rejected candidates, every candidate's scores, the
        calibration and the report table (JSON-able)."""
        return _jsonable(
            {
                "series": list(self.series),
                "rigid_refitted": list(self.rigid),
                "noise_m": self.noise_m,
                "naming": "blocked cross-validation inside each training series",
                "named": self.named,
                "steps": [
                    {
                        k: v
                        for k, v in st.items()
                        if k not in ("cv_before", "fits_better", "predicts_better")
                    }
                    | {"parameters": {n: list(vs) for n, vs in st["parameters"].items()}}
                    for st in self.steps
                ],
                "rejected": [
                    {k: e[k] for k in ("series", "round", "effect", "cv_gain", "delta_bic")}
                    for e in self.rejected
                ],
                "candidates": self.candidates_tried,
                "calibration_parameters": {
                    k: {n: list(vs) for n, vs in f.parameters().items()}
                    for k, f in self.calibration.fitted.items()
                },
                "fixed_unidentifiable": {
                    k: f.identifiability["dropped"] for k, f in self.calibration.fitted.items()
                },
                "table": self.table(),
            }
        )


def _term(fit: PoseFit, series: PoseSeries) -> dict[str, Any]:
    """The term report of a fit with maps (`map_report`)."""
    rep = map_report(fit, series)
    return {"variable": "joint angles", "words": rep["words"], **rep}


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


@serial_blas
def run_workflow(
    series: dict[str, PoseSeries],
    *,
    candidates: Sequence[str] = CANDIDATES,
    rigid: Sequence[str] = ("camera", "probe"),
    max_steps: int = 6,
    min_gain: float = MIN_CV_GAIN,
    prior_grid: Sequence[tuple[float, float]] = MAP_PRIOR_GRID,
    progress: Callable[[str], None] | None = None,
) -> Workflow:
    """The discrepancy workflow on pose series, each series naming on its own.

    Start: the nominal rigid model (only camera←base and flange←probe fitted) on every
    series, whose residuals set the block weights. Then, on each series alone
    (`_pose_selection.select`): each round scores every remaining candidate added to the
    effects named on that series by the blocked cross-validation error inside it (one
    Gauss–Newton step per left-out region of joint space); the candidate that lowers it
    most is named if it does so by at least `min_gain` (mean of the relative decreases of
    the held-out position and angle RMS); the maps' prior (σ_f, ℓ) is chosen from
    `prior_grid` the same way. A candidate that fits the series better (ΔBIC > 0) but
    fails the cross-validation is recorded as rejected (over-fitting). Stops when no
    candidate qualifies or after `max_steps`. Every named model is then frozen and
    predicts the other series with only the `rigid` transforms refitted: out-of-sample
    validation, reported and never used to name.
    """
    say = progress or (lambda _m: None)
    noise = {k: tracker_noise(s) for k, s in series.items()}
    nz = [v for v in noise.values() if v > 0]
    if nz:  # same tracker: a series without reported std gets the others' noise level
        noise = {k: (v if v > 0 else float(np.mean(nz))) for k, v in noise.items()}
    say("nominal rigid fits")
    # every fit in one layout: one compilation of each normal-equation kernel per series
    layout = uses_maps(candidates)
    nominal = _each(lambda k: fit_poses(series[k], rigid=rigid, maps_layout=layout), series)
    bsig = {k: v.block_sigma for k, v in nominal.items()}

    def name_on(k: str) -> tuple[Selection, list[dict[str, PoseFit]]]:
        """The effects named on series k, and what each step predicts of the others."""
        sel = select(
            series[k],
            nominal[k],
            candidates,
            rigid=rigid,
            max_steps=max_steps,
            min_gain=min_gain,
            prior_grid=prior_grid,
            progress=say,
        )
        say(f"{k}: cross-series validation")
        cross = [
            {
                t: nominal[t]
                if k_step == 0
                else cross_predict_weighted(f, series[t], rigid, bsig[t])
                for t in series
                if t != k
            }
            for k_step, f in enumerate(sel.fits)
        ]
        return sel, cross

    def calibrate() -> CrossSeries:
        say("kinematic calibration")
        return evaluate(CALIBRATION, series, rigid, bsig, maps_layout=layout)

    # the kinematic calibration takes the first thread a series leaves
    done = _concurrently({**{k: functools.partial(name_on, k) for k in series}, "": calibrate})
    calib = done.pop("")
    selections = {k: v[0] for k, v in done.items()}
    cross = {k: v[1] for k, v in done.items()}
    return Workflow(
        series=tuple(series),
        rigid=tuple(rigid),
        noise_m=noise,
        selections=selections,
        cross=cross,
        calibration=calib,
        data=dict(series),
    )


def cross_predict_weighted(
    source: PoseFit, target: PoseSeries, rigid: Sequence[str], block_sigma: tuple[float, float]
) -> PoseFit:
    """`cross_predict` with the target's block weights given."""
    return fit_poses(target, fixed=source, rigid=rigid, block_sigma=block_sigma)


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
