"""Discrepancy discovery (DESIGN section 7): what is the nominal model missing?

Fit the nominal model (bundle calibration); compare prediction and measurement; localise
the disagreement (time, program segment, joint angles, speed and acceleration, LED,
emission angle); score every candidate effect of the library at once with Rao's score
test (the Gauss–Newton predicted χ² decrease of adding it, χ²(k) under the null) and
BIC, with the noise level estimated from the data's static segments (not from the fit's
own residual, which contains what is missing); refit with the best significant one and
name it when the refit's likelihood-ratio test confirms it; repeat until nothing
significant remains; finally test whether structured residual is left and, if so,
report where it lives — never forcing a library name on it: per variable, the fraction
of the held-out gap that a smooth function of it alone removes (`Localisation`), ranked.

The **gap** is the RMS of the systematic disagreement with the noise taken out:
``sqrt(max(0, mean|r|² − mean 3σ̂²))`` over all LED observations [m].
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import UserError
from ..model import LIBRARY, dictionary, is_effect, term
from ..recording import Recording
from ._discovery_state import (
    Search,
    SearchState,
    Step as Step,
    observations,
    start,
)
from ._discovery_steps import (
    ALPHA as ALPHA,
    INDISTINCT_BIC as INDISTINCT_BIC,
    MAX_REFITS as MAX_REFITS,
    constructed_step,
    equivalence_step,
    maps_step,
    search_rounds,
    simpler_model_step,
)
from ._gap_localisation import Localisation as Localisation, label as label, localise
from ._heldout import HELDOUT_BLOCKS as HELDOUT_BLOCKS
from ._residual_stats import ALPHA_STRUCTURE as ALPHA_STRUCTURE, binned_rms, structure

#: recordings shorter than this many frames are searched with every fit in the space of
#: all candidates (one compilation); longer ones in a space per round. A fit in the space
#: of the 47 candidates of a 6-joint robot costs ~0.18 ms per frame more than one in its
#: own, a new space ~12 s of compilation (2-core machine); a search makes ~10 fits in ~3
#: spaces, so the two break even near 20 000 frames
SHARED_SPACE_FRAMES = 20_000


@dataclasses.dataclass(frozen=True)
class DiscrepancyResult:
    """What the workflow found. `structure` lists, per variable, the residual-structure
    test after the last step (`statistic`, `dof`, `p_value`, `significant`; the test
    that steers the search), `structure_before` the same of the nominal fit.
    `localisation` ranks the variables by where the nominal fit's gap lives (the fraction
    of the held-out gap a smooth function of each alone removes, ± its jackknife σ;
    `Localisation`), `localisation_after` the same of the final fit's gap when it is left
    above its floor (else None).
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
    localisation: Localisation | None
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
    structure_before: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    localisation_after: Localisation | None = None

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
        """Where the gap left lives: the variables a smooth function of which alone
        removes a fraction of the held-out gap more than 2σ above zero, the largest
        first (`localisation_after`); empty when the gap is within its floor."""
        return [] if self.localisation_after is None else self.localisation_after.localised

    def to_json(self) -> dict[str, Any]:
        """DESIGN section 8: gap_before_m, steps, gap_after_m, unexplained (+ details).

        ``localisation_before`` and ``localisation_after`` (null when the gap is within
        its floor) hold the ranking of `Localisation.to_json` (``{"gap_m", "floor_m",
        "frames", "ranking": [{"variable", "fraction", "sigma"}]}``, the largest fraction
        first, with ``"words"``); ``unexplained_where`` lists the variables of
        ``localisation_after`` whose fraction is more than 2σ above zero. Renamed: the χ²
        structure test of the nominal fit, formerly ``localisation_before``, is
        ``structure_before`` (``structure_after`` is unchanged); ``unexplained_where``
        formerly listed the variables that test found significant, by χ²/dof."""
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
                    "equally_supported": list(s.equivalent),
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
            "structure_before": self.structure_before,
            "localisation_before": _localisation_json(self.localisation, "the nominal model's gap"),
            "localisation_after": _localisation_json(self.localisation_after, "the gap left"),
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


def _localisation_json(loc: Localisation | None, what: str) -> dict[str, Any] | None:
    return None if loc is None else {**loc.to_json(), "words": loc.words(what)}


def discover(
    rec: Recording,
    *,
    candidates: tuple[str, ...] | None = None,
    max_steps: int = 4,
    progress=None,
    include: tuple[str, ...] = (),
    construct: bool = True,
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
    them). Last, when the gap is still above its floor with structure against joint
    angles, those joints' angle error maps (`robtraj.model.joint_maps`, a periodic error
    of many cycles per revolution) are offered and searched by the same rounds
    (`maps_step`); they come last so that a library effect or a dictionary term that
    explains the structure is named as such, not as a map standing in for it. When
    structure is left after them (and `construct`), terms built from the recording's
    signals — a joint's angle error as a function of one or two joint angles or gravity
    torques, `robtraj.model._constructed` — are screened at once and the strongest
    searched by the same rounds (`constructed_step`), at a significance divided by the
    number screened.
    """
    from ..estimate.calibration import library_space

    say = progress or (lambda _msg: None)
    candidates, include = _search_set(rec, candidates, include)
    say("emission angles and the noise model of the recording")
    obs = observations(rec)
    say("nominal fit")
    # fits share a space (one compilation): that of every candidate on short recordings,
    # else per round that of the named effects and the candidates it may refit
    shared = library_space(candidates, include) if rec.n_frames < SHARED_SPACE_FRAMES else None
    search, state = start(obs, candidates, include, shared, say)
    state = search_rounds(search, state, max_steps)
    # a simpler model: one dictionary term alone in place of what was named
    state = simpler_model_step(search, state)
    # structure left against joint angles: their angle error maps
    state = maps_step(search, state, max_steps)
    # structure still left: terms built from the recording's signals
    if construct:
        state = constructed_step(search, state, max_steps)
    # two stories the recording supports equally: said, with the poses that tell them apart
    state = equivalence_step(search, state)
    return _result(search, state)


def where_gap_lives(
    rec: Recording, *, include: tuple[str, ...] = (), progress=None
) -> Localisation:
    """Where the gap of the nominal model (with the effects `include`d) lives on `rec`:
    the variables ranked by the fraction of the held-out gap that a smooth function of
    each alone removes (`Localisation`), as `discover` reports it before naming
    anything (`DiscrepancyResult.localisation`), without the search."""
    say = progress or (lambda _msg: None)
    _, include = _search_set(rec, (), include)
    say("emission angles and the noise model of the recording")
    obs = observations(rec)
    say("nominal fit")
    search, state = start(obs, (), include, None, say)
    say("where the gap lives")
    return _where(search, search.nominal, state.floor, ())


def _search_set(
    rec: Recording, candidates: tuple[str, ...] | None, include: tuple[str, ...]
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The candidates to search (default: the library and the robot's dictionary terms)
    and the effects the model has from the start (the robot log's clock effects first),
    none in both; `UserError` for a name that is no effect."""
    from ..estimate import clock_effects

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
    return candidates, include


def _result(search: Search, state: SearchState) -> DiscrepancyResult:
    """The result of the search that ended in `state`: the final model reported with
    the cluster-robust σ, the residual structure and binned RMS before and after, and
    the named terms' residual against their variables."""
    obs = search.obs
    current = state.current
    if not state.robust:
        current = search.reported(current, state.named, state.space)
    nominal = search.nominal.residuals
    before = {
        k: binned_rms(nominal, obs.variables, k)
        for k in ("time", "joint 2", "emission angle")
        if k in obs.variables
    }
    left = structure(current.residuals, search.aligned_weights, obs.variables)
    search.say("where the gap lives")
    above = state.gaps[-1] > state.floor
    term_residuals = {}
    for name in state.named:
        t = term(name)
        if t is not None and t.frame_variable in obs.variables:
            v = t.frame_variable
            term_residuals[v] = (
                binned_rms(nominal, obs.variables, v),
                binned_rms(current.residuals, obs.variables, v),
            )
    return DiscrepancyResult(
        gap_before_m=state.gaps[0],
        steps=list(state.steps),
        gap_after_m=state.gaps[-1],
        gap_floor_m=state.floor,
        unexplained=above and any(v["significant"] for v in left.values()),
        structure=left,
        localisation=_where(search, search.nominal, search.floor(search.nominal), search.shared),
        noise_sigma_m=obs.sigma,
        calibration=current,
        gaps=list(state.gaps),
        residual_before=before,
        residual_after={k: binned_rms(current.residuals, obs.variables, k) for k in before},
        noise=obs.noise,
        rejected=list(state.rejected),
        stopped=state.stopped,
        term_residuals=term_residuals,
        included=search.include,
        structure_before=structure(nominal, search.aligned_weights, obs.variables),
        localisation_after=_where(search, current, state.floor, state.space) if above else None,
    )


def _where(search: Search, res, floor: float, space) -> Localisation:
    """Where the gap of the fit `res` (in `space`) lives (`localise`), on the held-out
    check's folds."""
    obs = search.obs
    return localise(
        obs.rec,
        res,
        res.residuals,
        search.aligned_weights,
        search.var3,
        obs.localised,
        obs.heldout.block,
        floor=floor,
        space=space or (),
    )
