"""Naming effects on one pose series by blocked cross-validation inside it.

Greedy forward selection: from the nominal rigid model, each round scores every
remaining candidate added to the effects named so far by its blocked cross-validation
error on the series (`_pose_cv`: regions of joint space left out one at a time, one
Gauss–Newton step each from the current model's linearisation), names the candidate
that lowers it most if it does so by at least `MIN_CV_GAIN`, refits, and repeats. A
candidate with a Gaussian prior (the joint angle error maps) is scored at every
(σ_f, ℓ) of a small grid and keeps the one with the lowest error: its hyper-parameters
are chosen inside the series too. Nothing outside the series takes part.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import scipy.linalg

from .._blas import serial_blas
from ._pose_cv import Linearisation, RegionSystems, cv_error, gain, posterior
from ._pose_fit import (
    HARMONIC_TERMS,
    MAP_TERMS,
    N_PARAMS,
    PoseFit,
    _data,
    _free_mask,
    _resized,
    _weights,
    fit_poses,
    identifiable,
    linearise,
    map_prior_of,
    map_terms_of,
    marginal,
    n_params,
    parse_effect_spec,
    regions,
    structure_normal,
    uses_maps,
)
from ._pose_series import PoseSeries

#: smallest relative decrease of the cross-validation error that names an effect (the
#: mean of the decreases of the held-out position RMS and rotation-angle RMS)
MIN_CV_GAIN = 0.02


@dataclasses.dataclass(frozen=True)
class Selection:
    """The effects named on one series, step by step.

    `fits`: the nominal rigid fit and the fit after each named effect; `steps`: one dict
    per named effect (``round``, ``effect``, ``cv_before``, ``cv`` — RMS and mean of the
    held-out position [m] and angle [rad] — ``cv_gain``, ``delta_bic``, ``map_prior``
    where the effect carries one); `candidates`: every candidate scored, per round;
    `rejected`: those that fitted the series better (ΔBIC > 0) but did not lower its
    cross-validation error by `MIN_CV_GAIN` (over-fitting), with the round."""

    series: str
    fits: list[PoseFit]
    steps: list[dict[str, Any]]
    candidates: list[dict[str, Any]]
    rejected: list[dict[str, Any]]

    @property
    def named(self) -> list[str]:
        return [s["effect"] for s in self.steps]

    @property
    def final(self) -> PoseFit:
        return self.fits[-1]


def group_of(spec: str) -> str:
    """What naming `spec` takes out of the candidates: its effect (all of
    ``joint_compliance`` with ``joint_compliance[1,2]``; every map with ``joint_map``),
    or the term itself."""
    if spec in HARMONIC_TERMS:
        return spec
    if spec in MAP_TERMS:
        return "joint_map"
    return parse_effect_spec(spec)[0]


def _chi2(lin: Linearisation, delta: np.ndarray) -> float:
    """The data's χ² after the Gauss–Newton step `delta` from the linearisation."""
    return float(lin.cost - 2.0 * lin.b @ delta + delta @ lin.h @ delta)


def _bic(chi2_before: float, chi2_after: float, n_res: int, dof: float) -> float:
    """ΔBIC: the likelihood ratio with the noise scale profiled, ``n·ln(χ²₀/χ²₁)``, minus
    ``dof·ln n`` (positive: the added parameters are supported)."""
    lr = n_res * math.log(max(chi2_before, 1e-300) / max(chi2_after, 1e-300))
    return float(lr - dof * math.log(n_res))


def _prior_dof(lin: Linearisation, prior: np.ndarray, free: np.ndarray) -> float:
    """Effective parameter count of the prior's entries: ``tr((H + Λ)⁻¹H)`` over them."""
    idx = np.flatnonzero(free)
    h, _ = posterior(lin, prior)
    on = np.diag(prior)[idx] > 0
    inv = scipy.linalg.cho_solve(scipy.linalg.cho_factor(h[np.ix_(idx, idx)]), np.eye(idx.size))
    return float(np.sum(inv[on] * lin.h[np.ix_(idx, idx)][:, on].T))


class _Round:
    """One round's linearisation of the current model and, per prior of the maps, the
    systems every candidate is scored from (`RegionSystems`, and the structural normal
    matrix with the knots marginalised for identifiability)."""

    def __init__(self, lin, h_struct, series, rigid):
        self.lin, self.h_struct, self.series, self.rigid = lin, h_struct, series, rigid
        self.maps = lin.theta.size > N_PARAMS
        self._cache = {}

    def score(self, effects, map_prior) -> dict[str, Any]:
        """``{"cv", "free", "steps", "prior"}`` of the model `effects` under `map_prior`."""
        p = self.lin.theta.size
        free0 = _free_mask(effects, self.rigid, self.series, self.maps)
        key = (map_prior, map_terms_of(effects))
        if key not in self._cache:
            pr = map_prior_of(effects, map_prior)
            lam = pr.dense(p) if pr.size else None
            h = self.h_struct if lam is None else self.h_struct + lam
            schur = marginal(h, free0) if self.maps else None
            self._cache[key] = (lam, schur, RegionSystems(self.lin, lam, free0))
        lam, schur, systems = self._cache[key]
        free, _ = identifiable(self.h_struct, free0, schur)
        steps = systems.steps(free)
        return {"cv": cv_error(self.lin, steps), "free": free, "steps": steps, "prior": lam}


@serial_blas
def select(
    series: PoseSeries,
    nominal: PoseFit,
    candidates: Sequence[str],
    *,
    rigid: Sequence[str] = ("camera", "probe"),
    max_steps: int = 6,
    min_gain: float = MIN_CV_GAIN,
    prior_grid: Sequence[tuple[float, float]] = (),
    progress: Callable[[str], None] | None = None,
) -> Selection:
    """Greedy selection on `series` alone (module docstring), from its `nominal` rigid
    fit (whose block weights every fit keeps). `prior_grid`: the (σ_f, ℓ) [rad] tried
    for the maps (`robtraj.model.MAP_PRIOR_GRID`; empty: the terms' own prior), when
    they are first scored, and again for the final model when effects were named after
    them (which take part of what the maps carried); its last step's fit is then refitted
    with that prior (``final_map_prior``)."""
    say = progress or (lambda _m: None)
    label = regions(series)
    bsig = nominal.block_sigma
    w = _weights(series, bsig)
    n_res = 6 * series.n
    current, named, map_prior = nominal, [], None
    fits, steps, tried, rejected = [nominal], [], [], []
    structural = {}

    def h_struct(p: int) -> np.ndarray:
        """The normal matrix at the effects' zero (the nominal fit's rigid transforms),
        for identifiability: the model's structure, computed once per layout."""
        if p not in structural:
            at = _resized(nominal.theta[:12], p)
            structural[p] = structure_normal(at, nominal.z0, nominal.x0, series, w)
        return structural[p]

    for rnd in range(1, max_steps + 1):
        taken = {group_of(c) for c in named}
        remaining = [c for c in candidates if group_of(c) not in taken]
        if not remaining:
            break
        say(f"{series.name}, round {rnd}: cross-validating {len(remaining)} candidates")
        maps = uses_maps([*named, *remaining])
        p = n_params(maps)
        theta = _resized(current.theta, p)
        data = _data(current.z0, current.x0, series, w, False)
        lin = linearise(theta, data, label)
        rnd_ = _Round(lin, h_struct(p), series, rigid)
        has_maps = bool(map_terms_of(named))
        now = rnd_.score(named, map_prior)
        chi2_now = _chi2(lin, now["steps"][-1])
        dense_now = int(np.sum(now["free"][12:N_PARAMS]))
        scored = {}
        for cand in remaining:
            effects = (*named, cand)
            new_map = bool(map_terms_of([cand])) and not has_maps
            grid = list(prior_grid) if new_map and prior_grid else [map_prior]
            table, best = [], None
            for mp in grid:
                res = rnd_.score(effects, mp)
                g = gain(now["cv"], res["cv"])
                if new_map and mp is not None:
                    table.append({"sigma_f_rad": mp[0], "length_scale_rad": mp[1], **res["cv"]})
                if best is None or g > best[0]:
                    best = (g, mp, res)
            g, mp, res = best
            dof = float(np.sum(res["free"][12:N_PARAMS])) - dense_now
            if new_map:
                dof += _prior_dof(lin, res["prior"], res["free"])
            entry = {
                "round": rnd,
                "effect": cand,
                "cv_before": now["cv"],
                "cv": res["cv"],
                "cv_gain": g,
                "cv_gain_position": 1 - res["cv"]["pos_rms_m"] / now["cv"]["pos_rms_m"],
                "cv_gain_angle": 1 - res["cv"]["ang_rms_rad"] / now["cv"]["ang_rms_rad"],
                "delta_bic": _bic(chi2_now, _chi2(lin, res["steps"][-1]), n_res, dof),
                "dof": dof,
                "predicts_better": g >= min_gain,
            }
            entry["fits_better"] = entry["delta_bic"] > 0
            if mp is not None and map_terms_of(effects):
                entry["map_prior"] = {"sigma_f_rad": mp[0], "length_scale_rad": mp[1]}
                if table:
                    entry["map_prior"]["grid"] = table
            tried.append(entry)
            scored[cand] = (entry, mp, theta + res["steps"][-1])
        for entry, _, _ in scored.values():
            if entry["fits_better"] and not entry["predicts_better"]:
                rejected.append(entry)
        eligible = [c for c, (e, _, _) in scored.items() if e["predicts_better"]]
        if not eligible:
            break
        best_c = max(eligible, key=lambda c: scored[c][0]["cv_gain"])
        entry, mp, theta_step = scored[best_c]
        if map_terms_of([best_c]) or has_maps:
            map_prior = mp
        named.append(best_c)
        say(f"{series.name}: named {best_c} (cross-validation gain {100 * entry['cv_gain']:.1f} %)")
        # refitted from the Gauss–Newton step the scoring took (one or two steps more)
        p_named = n_params(uses_maps(named))
        current = fit_poses(
            series,
            estimate=tuple(named),
            init=dataclasses.replace(current, theta=_resized(theta_step, p_named)),
            block_sigma=bsig,
            map_prior=map_prior,
            rigid=rigid,
            structure=h_struct(p_named),
        )
        fits.append(current)
        steps.append(dict(entry))
    if map_terms_of(named) and prior_grid and len(named) > 1:
        # the maps' prior chosen again for the final model: the effects named after them
        # have taken part of what they carried
        say(f"{series.name}: the maps' prior of the final model")
        theta = current.theta
        if rnd_.lin.theta.size != theta.size or not np.array_equal(rnd_.lin.theta, theta):
            # (the last round linearised at `current` where it named nothing)
            lin = linearise(theta, _data(current.z0, current.x0, series, w, False), label)
            rnd_ = _Round(lin, h_struct(theta.size), series, rigid)
        table = [(mp, rnd_.score(named, mp)["cv"]) for mp in prior_grid]
        best = min(table, key=lambda x: _cost(x[1]))[0]
        steps[-1]["final_map_prior"] = {
            "sigma_f_rad": best[0],
            "length_scale_rad": best[1],
            "grid": [{"sigma_f_rad": mp[0], "length_scale_rad": mp[1], **cv} for mp, cv in table],
        }
        if tuple(best) != tuple(map_prior):
            map_prior = tuple(best)
            current = fit_poses(
                series,
                estimate=tuple(named),
                init=current,
                block_sigma=bsig,
                map_prior=map_prior,
                rigid=rigid,
                structure=h_struct(theta.size),
            )
            fits[-1] = current
    return Selection(series.name, fits, steps, tried, rejected)


def _cost(cv: dict[str, float]) -> float:
    """A model's cross-validation cost when its own prior is chosen: the geometric mean of
    the held-out position and angle RMS (the order `gain` gives against any reference)."""
    return math.sqrt(cv["pos_rms_m"] * cv["ang_rms_rad"])
