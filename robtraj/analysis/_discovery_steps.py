"""The steps of the discrepancy search (`robtraj.analysis.discrepancy.discover`): rounds
that score every candidate, refit the significant ones and name the first the refit and
the held-out blocks confirm (with the deadband of a motion term profiled, and the
effects a term made redundant dropped), then the test of one dictionary term alone as a
simpler model. Each step takes the `SearchState` and returns a new one."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..model import MOTION_THRESHOLD, joint_maps, term
from ._discovery_state import Search, SearchState, Step
from ._effect_statistics import effect_parameters, free_count, significance, without
from ._heldout import vuong
from ._residual_stats import structure
from ._term_report import term_report

#: significance of a candidate effect, before the Bonferroni division by the candidates
ALPHA = 0.01
#: significant candidates refitted per round, strongest score first: the score test is
#: the refit's likelihood ratio to first order, so a round whose strongest few all fail
#: the refit or the held-out check has nothing further down to name
MAX_REFITS = 5
#: ΔBIC below which the recording does not tell two candidates apart (Kass and Raftery's
#: "very strong" evidence starts at 10)
INDISTINCT_BIC = 10.0
#: significant candidates besides the named one compared with it on the held-out blocks
RIVALS = 2
#: how far below the named effect's score statistic a rival's may lie: absolute, and
#: relative (the score test's first-order error grows with the effect)
RIVAL_MARGIN = (100.0, 1e-3)
#: Vuong's z on the held-out blocks below which a rival is as well supported as the named
#: effect (one-sided 2.5 %)
Z_EQUIVALENT = 1.96

#: a candidate the refit and the held-out check confirmed: (effect, its refit, its score,
#: the space of the refit)
_Confirmed = tuple[str, Any, dict[str, Any], tuple[str, ...]]


def search_rounds(search: Search, state: SearchState, max_steps: int) -> SearchState:
    """Up to `max_steps` rounds, until one stops the search; after the last, `stopped`
    says whether the gap is within its floor."""
    for _ in range(max_steps):
        state = _round(search, state)
        if state.stopped:
            return state
    within = state.gaps[-1] <= state.floor
    return dataclasses.replace(state, stopped="gap_within_floor" if within else "max_steps")


def _round(search: Search, state: SearchState) -> SearchState:
    """One round: the score test of every remaining candidate (Bonferroni over them),
    the refit of the strongest significant ones in one space, and the naming of the
    first confirmed; `stopped` set when the gap is within its floor, nothing is left to
    try, nothing qualifies or no structure is left."""
    if state.gaps[-1] <= state.floor:
        return dataclasses.replace(state, stopped="gap_within_floor")
    remaining = [c for c in search.candidates if c not in state.named and c not in state.tried]
    if not remaining:
        return dataclasses.replace(state, stopped="no_candidates")
    search.say(f"score test of {len(remaining)} candidate effects")
    alpha = ALPHA / max(len(remaining), search.screened)
    scores = _score_tests(search, state.current, remaining)
    significant = [
        c
        for c in sorted(scores, key=lambda c: -scores[c]["delta_bic"])
        if scores[c]["p_value"] < alpha and scores[c]["delta_bic"] > 0
    ]
    space = search.shared or tuple(dict.fromkeys((*state.named, *significant[:MAX_REFITS])))
    state, confirmed = _first_confirmed(search, state, significant[:MAX_REFITS], alpha, space)
    if confirmed is None:
        return dataclasses.replace(state, stopped="nothing_qualifies")
    state = _name(search, state, confirmed, scores, significant)
    # nothing structured left against any variable: no further effect can stand out
    left = structure(state.current.residuals, search.aligned_weights, search.obs.variables)
    if not any(v["significant"] for v in left.values()):
        return dataclasses.replace(state, stopped="no_structure")
    return state


def _score_tests(search: Search, res, effects) -> dict[str, dict[str, Any]]:
    """Rao's score test of adding each of `effects` to the fit `res` (one pass over the
    recording, `robtraj.estimate.calibration.score_effects`); effects it cannot move
    (no dof) left out."""
    from ..estimate.calibration import score_effects

    return {
        c: significance(
            v["statistic"], v["dof"], search.n_obs, test="score", statistic=v["statistic"]
        )
        for c, v in score_effects(search.obs.rec, res, effects, weights=search.obs.weights).items()
        if v["dof"] > 0
    }


def _first_confirmed(
    search: Search, state: SearchState, candidates, alpha: float, space: tuple[str, ...]
) -> tuple[SearchState, _Confirmed | None]:
    """The first of `candidates` whose refit (in `space`) passes the likelihood-ratio test
    at `alpha` with a positive ΔBIC and lowers the held-out gap by more than the floor;
    None if none does. The state returned holds the held-out gap (of the confirmed one)
    and the candidates that failed the held-out check (`rejected`)."""
    from ..estimate.calibration import fit

    heldout = search.obs.heldout
    for cand in candidates:
        search.say(f"refitting with {cand}")
        own = _refit_space(cand, state.named, space, search.shared is not None)
        r = fit(
            search.obs.rec,
            estimate=(*state.named, cand),
            weights=search.obs.weights,
            init=state.current,
            space=own,
            robust_sigma=False,
        )
        k = free_count(r, cand)
        if k == 0:
            continue
        lr = float(state.current.chi2 - r.chi2)
        score = significance(lr, k, search.n_obs, likelihood_ratio=lr)
        if not (score["p_value"] < alpha and score["delta_bic"] > 0):
            continue
        search.say(f"held-out check of {cand}")
        state = _with_heldout_gap(search, state)
        after = heldout.gap((*state.named, cand), r, own)
        score.update(heldout_gap_before_m=state.heldout_gap, heldout_gap_after_m=after)
        if state.heldout_gap - after > state.floor:
            return dataclasses.replace(state, heldout_gap=after), (cand, r, score, own)
        state = dataclasses.replace(state, rejected=(*state.rejected, {"effect": cand, **score}))
    return state, None


def _refit_space(
    cand: str, named: tuple[str, ...], space: tuple[str, ...], shared: bool
) -> tuple[str, ...]:
    """The space `cand` is refitted in beside the `named` effects: the round's `space`,
    except for a joint angle error map when the search is not in one `shared` space:
    the named effects and the map alone. Every pass of a fit builds the normal equations
    of its whole space, and a held map's hundreds of knots cost more there, pass after
    pass, than one compilation of the smaller space."""
    t = term(cand)
    if shared or t is None or not t.knots:
        return space
    return tuple(dict.fromkeys((*named, cand)))


def _with_heldout_gap(search: Search, state: SearchState) -> SearchState:
    """`state` with the held-out gap of its model [m], computed when not yet known."""
    if state.heldout_gap is not None:
        return state
    gap = search.obs.heldout.gap(state.named, state.current, state.space)
    return dataclasses.replace(state, heldout_gap=gap)


def _name(
    search: Search,
    state: SearchState,
    confirmed: _Confirmed,
    scores: dict[str, dict[str, Any]],
    significant: list[str],
) -> SearchState:
    """Name the `confirmed` candidate: its deadband profiled (a motion term), the
    candidates the score test cannot tell from it noted, the effects it made redundant
    dropped (a dictionary term), the fit reported with the cluster-robust σ, and the
    step added."""
    best, current, score, space = confirmed
    state = dataclasses.replace(state, current=current, space=space, robust=False)
    state, score, interval = _deadband(search, state, best, score)
    # candidates the score test cannot tell from the named one
    alternatives = tuple(
        c
        for c in significant
        if c != best and scores[best]["delta_bic"] - scores[c]["delta_bic"] < INDISTINCT_BIC
    )
    state = dataclasses.replace(state, named=(*state.named, best))
    state, replaces = _drop_redundant(search, state, best)
    if not state.robust:
        reported = search.reported(state.current, state.named, state.space)
        state = dataclasses.replace(state, current=reported, robust=True)
    state = _with_step(search, state, best, score, scores, replaces, alternatives, interval)
    search.say(f"named {best}: gap {state.gaps[-2] * 1e6:.1f} → {state.gaps[-1] * 1e6:.1f} µm")
    if replaces:
        search.say(f"{best} replaces {', '.join(replaces)}")
    return state


def _deadband(search: Search, state: SearchState, effect: str, score: dict[str, Any]):
    """For a term of the motion sign: the model with `effect` refitted at its profiled
    motion threshold (with the cluster-robust σ) and its held-out gap in `score`, and the
    threshold's interval [rad/s]; any other effect unchanged, with no interval."""
    t = term(effect)
    if t is None or not t.motion:
        return state, score, None
    search.say(f"deadband of {effect}: profile of the motion threshold")
    named = (*state.named, effect)
    _, current, interval = _profile_motion_threshold(search, named, state.current, state.space)
    heldout_gap = search.obs.heldout.gap(named, current, state.space)
    state = dataclasses.replace(state, current=current, robust=True, heldout_gap=heldout_gap)
    return state, {**score, "heldout_gap_after_m": heldout_gap}, interval


def _drop_redundant(
    search: Search, state: SearchState, effect: str
) -> tuple[SearchState, tuple[str, ...]]:
    """After naming dictionary term `effect`: each effect named before it that is no
    longer needed next to it dropped, in order; with the names dropped."""
    if term(effect) is None:
        return state, ()
    replaces = []
    for old in [n for n in state.named if n != effect]:
        dropped = _without_if_redundant(search, state, old, effect)
        if dropped is not None:
            state = dropped
            replaces.append(old)
    return state, tuple(replaces)


def _without_if_redundant(
    search: Search, state: SearchState, old: str, effect: str
) -> SearchState | None:
    """The model refitted without `old`; None while `old` is still needed next to
    `effect`: leaving it out fails the likelihood-ratio test (Bonferroni over all
    candidates) and raises the held-out gap by more than the floor, as when it was named."""
    from ..estimate.calibration import fit

    keep = tuple(n for n in state.named if n != old)
    search.say(f"is {old} still needed next to {effect}?")
    r = fit(
        search.obs.rec,
        estimate=keep,
        weights=search.obs.weights,
        init=without(state.current, old),
        space=state.space,
        robust_sigma=False,
    )
    k = free_count(state.current, old)
    lr = float(r.chi2 - state.current.chi2)
    test = significance(lr, max(k, 1), search.n_obs)
    count = max(len(search.candidates), search.screened, 1)
    needed = test["p_value"] < ALPHA / count and test["delta_bic"] > 0
    if needed:
        h = search.obs.heldout.gap(keep, r, state.space)
        needed = h - state.heldout_gap > state.floor
    if needed:
        return None
    heldout_gap = search.obs.heldout.gap(keep, r, state.space)
    return dataclasses.replace(
        state,
        named=keep,
        current=r,
        robust=False,
        tried=state.tried | {old},
        heldout_gap=heldout_gap,
    )


def _with_step(
    search: Search,
    state: SearchState,
    effect: str,
    score: dict[str, Any],
    candidates: dict[str, dict[str, Any]],
    replaces: tuple[str, ...],
    alternatives: tuple[str, ...] = (),
    interval: tuple[float, float] | None = None,
) -> SearchState:
    """`state` with the step that names `effect` (fitted as `state.current`): its
    parameters, the gap after it and the new floor, and a dictionary term's report."""
    rec, current = search.obs.rec, state.current
    gap = search.gap(current)
    step = Step(
        effect,
        effect_parameters(current, effect),
        gap,
        score,
        candidates,
        term_report(rec, current, effect, search.obs.angles, interval),
        replaces,
        alternatives,
    )
    return dataclasses.replace(
        state, gaps=(*state.gaps, gap), floor=search.floor(current), steps=(*state.steps, step)
    )


def simpler_model_step(search: Search, state: SearchState) -> SearchState:
    """When library effects were named: the dictionary term that alone has a lower BIC
    than the whole named model replaces it (a step whose `replaces` lists what was named)
    if its held-out gap is no worse by more than the floor; else it is `rejected`."""
    offered = [c for c in search.candidates if term(c) is not None and c not in state.named]
    if not (offered and any(term(n) is None for n in state.named)):
        return state
    search.say(f"is one dictionary term a simpler model than {', '.join(state.named)}?")
    swap = _simpler_model(search, state, offered)
    if swap is None:
        return state
    c, r, score, tests, swap_space = swap
    state = _with_heldout_gap(search, state)
    h = search.obs.heldout.gap((c,), r, swap_space)
    score.update(heldout_gap_before_m=state.heldout_gap, heldout_gap_after_m=h)
    if not h <= state.heldout_gap + state.floor:
        return dataclasses.replace(state, rejected=(*state.rejected, {"effect": c, **score}))
    search.say(f"{c} alone replaces {', '.join(state.named)}")
    replaced = state.named
    current = search.reported(r, (c,), swap_space)
    state = dataclasses.replace(state, named=(c,), heldout_gap=h, current=current, space=swap_space)
    return _with_step(search, state, c, score, tests, replaced)


def _profile_motion_threshold(search: Search, named, current, space):
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
            search.obs.rec,
            estimate=tuple(named),
            weights=search.obs.weights,
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


def _simpler_model(search: Search, state: SearchState, offered):
    """The dictionary term that alone has a lower BIC than the model `state.named`
    (fitted as `state.current`), with its refit (no cluster-robust σ), its score, the
    score tests from the nominal model (that of the search; refitted here without the
    effects it included) and the space of the refit; None if no term does. The terms
    tried are the `MAX_REFITS` strongest by the score test from the nominal model,
    refitted in one space (the shared one, else their own)."""
    from ..estimate.calibration import fit

    rec, weights, n_obs, shared = search.obs.rec, search.obs.weights, search.n_obs, search.shared
    nominal = None if search.include else search.nominal
    if nominal is None:
        nominal = fit(rec, weights=weights, space=shared or (), robust_sigma=False)
    tests = _score_tests(search, nominal, offered)
    current = state.current
    k_now = sum(free_count(current, e) for e in state.named)
    bic_now = current.chi2 + k_now * np.log(n_obs)
    best = None
    top = [
        c for c in sorted(tests, key=lambda c: -tests[c]["delta_bic"]) if tests[c]["delta_bic"] > 0
    ]
    space = shared or tuple(top[:MAX_REFITS])
    for c in top[:MAX_REFITS]:
        r = fit(rec, estimate=(c,), weights=weights, init=nominal, space=space, robust_sigma=False)
        k = free_count(r, c)
        bic = r.chi2 + k * np.log(n_obs)
        if k and bic < bic_now and (best is None or bic < best[2]):
            best = (c, r, bic, k)
    if best is None:
        return None
    c, r, bic, k = best
    lr = float(nominal.chi2 - r.chi2)
    score = significance(
        lr, k, n_obs, likelihood_ratio=lr, delta_bic_against_replaced=float(bic_now - bic)
    )
    return c, r, score, tests, space


def equivalence_step(search: Search, state: SearchState) -> SearchState:
    """For each named effect: its rivals (`rivals`) each fitted in its place (the rest of
    the model as named); one that Vuong's test on the held-out blocks does not find worse
    (z below `Z_EQUIVALENT`) is equally supported (`Step.equivalent`), with the static
    poses that would tell the two apart (`separating_poses`)."""
    steps = []
    for step in state.steps:
        rivals = _rivals(step) if step.effect in state.named else ()
        if rivals:
            space = search.shared or tuple(dict.fromkeys((*state.space, *rivals)))
            named = search.obs.heldout.chi2(state.named, state.current, space)
            found = (_equivalent(search, state, step, r, named, space) for r in rivals)
            step = dataclasses.replace(step, equivalent=tuple(e for e in found if e))
        steps.append(step)
    return dataclasses.replace(state, steps=tuple(steps))


def _rivals(step: Step) -> tuple[str, ...]:
    """The candidates of `step`'s round that might explain as much: those the score test
    did not tell from it (`alternatives`) and the `RIVALS` next strongest significant
    ones (by ΔBIC) whose score statistic is within `RIVAL_MARGIN` of its own (two models
    whose predictions differ by D in χ² differ by about D in the statistic, and Vuong's z
    is about √D / 2: far beyond the margin no test on held-out blocks could find them
    equal)."""
    scores = step.candidates
    alpha = ALPHA / max(len(scores), 1)
    own = scores.get(step.effect, {}).get("statistic")
    if own is None:
        return step.alternatives
    margin = RIVAL_MARGIN[0] + RIVAL_MARGIN[1] * own
    strong = [
        c
        for c in sorted(scores, key=lambda c: -scores[c]["delta_bic"])
        if c != step.effect
        and scores[c]["p_value"] < alpha
        and scores[c]["delta_bic"] > 0
        and own - scores[c].get("statistic", -np.inf) <= margin
    ]
    return tuple(dict.fromkeys((*step.alternatives, *strong[:RIVALS])))


def _equivalent(search: Search, state: SearchState, step: Step, rival: str, named_chi2,
                space) -> dict | None:  # fmt: skip
    """`rival` in place of `step.effect`: Vuong's z and the held-out χ² by which it is
    worse than the named model (`named_chi2`, `HeldOut.chi2`), with the poses that tell
    the two apart, when z is below `Z_EQUIVALENT`; else None."""
    from ..estimate.calibration import fit
    from ._separating_poses import separating_poses

    obs = search.obs
    named = tuple(rival if e == step.effect else e for e in state.named)
    search.say(f"is {rival} in place of {step.effect} equally supported?")
    r = fit(obs.rec, estimate=named, weights=obs.weights, init=search.nominal, space=space,
            robust_sigma=False)  # fmt: skip
    z, worse = vuong(named_chi2, obs.heldout.chi2(named, r, space))
    if z >= Z_EQUIVALENT:
        return None
    poses = separating_poses(
        obs.rec, obs.noise, obs.angles, (step.effect, state.current), (rival, r)
    )
    return {
        "effect": rival,
        "heldout_z": z,
        "heldout_chi2_worse": worse,
        "next_poses": None if poses is None else poses.to_json(),
    }


def maps_step(search: Search, state: SearchState, max_steps: int) -> SearchState:
    """When the search ends above the floor with structure left against joint angles,
    those joints' angle error maps (`robtraj.model.joint_maps`: a periodic error that the
    dictionary's few harmonics cannot represent) are offered and searched by the same
    rounds; otherwise, and where the candidates hold maps already, `state` as it is."""
    if state.gaps[-1] <= state.floor or any(term(c) and term(c).knots for c in search.candidates):
        return state
    left = structure(state.current.residuals, search.aligned_weights, search.obs.variables)
    maps = tuple(
        name
        for name in joint_maps(search.obs.rec.robot.joints.shape[1])
        if left.get(term(name).frame_variable, {}).get("significant")
    )
    if not maps:
        return state
    search.say(f"structure left against {', '.join(term(m).frame_variable for m in maps)}: maps")
    offered = dataclasses.replace(search, candidates=maps, shared=None)
    return search_rounds(offered, dataclasses.replace(state, stopped=""), max_steps)


def constructed_step(search: Search, state: SearchState, max_steps: int) -> SearchState:
    """While the gap is above its floor with structure left: the joint angle errors built
    from the recording's signals (`robtraj.model._constructed`) screened at once on the
    fit's moments (`_constructed_terms.screen`), the strongest offered to a round of
    the search (score test, refit, held-out blocks) at the significance level divided by
    the number screened; up to `max_steps` rounds, each screening the model as it stands.
    They come after the dictionary and the maps: a fixed term that explains the structure
    is named as such."""
    from ._constructed_terms import screen

    for _ in range(max_steps):
        if state.gaps[-1] <= state.floor:
            return dataclasses.replace(state, stopped="gap_within_floor")
        left = structure(state.current.residuals, search.aligned_weights, search.obs.variables)
        if not any(v["significant"] for v in left.values()):
            return state
        search.say("constructing terms from the recording's signals")
        exclude = frozenset(state.named) | state.tried | {r["effect"] for r in state.rejected}
        found = screen(search, state, exclude)
        if not found.offered:
            return state
        offered = dataclasses.replace(
            search, candidates=found.offered, shared=None, screened=found.screened
        )
        before = state
        state = _round(offered, dataclasses.replace(state, stopped=""))
        if len(state.steps) > len(before.steps):
            state = _simpler_form(search, before, state)
        if state.stopped:
            return state
    return state


def _simpler_forms(effect: str) -> tuple[str, ...]:
    """The constructed terms simpler than constructed term `effect`: each of its two
    factors alone, and a joint angle's first harmonic as the angle itself (a linear
    error); those the dictionary or the library hold left out."""
    from ..model import (
        ConstructedFactor as Factor,
        constructed_groups as candidate_groups,
        constructed_name as name_of,
    )

    t = term(effect)
    forms = [(f,) for f in t.factors] if len(t.factors) == 2 else []
    if len(t.factors) == 1 and t.factors[0].harmonic == 1:
        f = t.factors[0]
        forms.append((Factor(f.signal, f.joint),))
    valid = {name_of(j, f) for j, f in candidate_groups(max(t.joint + 1, *(
        f.joint + 1 for f in t.factors)))}  # fmt: skip
    return tuple(n for n in (name_of(t.joint, f) for f in forms) if n in valid)


def _simpler_form(search: Search, before: SearchState, state: SearchState) -> SearchState:
    """After a constructed term was named (`state`, from `before`): a simpler form of it
    (`_simpler_forms`) in its place when its BIC is lower and its held-out gap no worse by
    more than the floor (a step whose `replaces` holds the term); else `state`."""
    from ..estimate.calibration import fit

    effect = state.steps[-1].effect
    if term(effect) is None or not term(effect).factors or effect not in state.named:
        return state
    forms = _simpler_forms(effect)
    if not forms:
        return state
    search.say(f"is a simpler form of {effect} as good?")
    n_obs = search.n_obs
    space = tuple(dict.fromkeys((*state.space, *forms)))

    def bic(res, named):
        return res.chi2 + sum(free_count(res, e) for e in named) * np.log(n_obs)

    bic_now = bic(state.current, state.named)
    best = None
    for form in forms:
        named = tuple(form if e == effect else e for e in state.named)
        r = fit(search.obs.rec, estimate=named, weights=search.obs.weights,
                init=without(state.current, effect), space=space, robust_sigma=False)  # fmt: skip
        if free_count(r, form) and bic(r, named) < (bic_now if best is None else best[2]):
            best = (form, r, bic(r, named), named)
    if best is None:
        return state
    form, r, b, named = best
    h = search.obs.heldout.gap(named, r, space)
    lr = float(before.current.chi2 - r.chi2)
    score = significance(lr, free_count(r, form), n_obs, likelihood_ratio=lr,
                         delta_bic_against_replaced=float(bic_now - b),
                         heldout_gap_before_m=state.steps[-1].score["heldout_gap_before_m"],
                         heldout_gap_after_m=h)  # fmt: skip
    if not h <= state.heldout_gap + state.floor:
        return dataclasses.replace(state, rejected=(*state.rejected, {"effect": form, **score}))
    search.say(f"{form} replaces {effect}")
    current = search.reported(r, named, space)
    state = dataclasses.replace(state, named=named, current=current, space=space,
                                robust=True, heldout_gap=h)  # fmt: skip
    return _with_step(search, state, form, score, state.steps[-1].candidates, (effect,))
