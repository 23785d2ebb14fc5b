"""What the discrepancy search holds: the observations and the nominal fit it measures
against (fixed while it runs), the model as it stands after each step, and the steps it
names. Every step of the search (`_discovery_steps`) takes a state and returns a new one."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from ..estimate import NoiseModel, observation_angles, observation_noise
from ..recording import Recording
from ._heldout import HeldOut
from ._residual_stats import aligned, frame_variables, gap, gap_floor, noise_share


@dataclasses.dataclass(frozen=True)
class Step:
    """One named effect: fitted `parameters` {name: (value, σ)} (SI units), the gap after
    adding it [m], and its `score` (likelihood ratio of the refit, dof, p-value, ΔBIC,
    and the held-out gaps before and after it [m]); `candidates`: the score tests of
    every candidate of the round; `term`: a dictionary term's report (variable,
    function, coefficients, words, where it acts); `replaces`: effects named before that
    it made redundant (dropped); `alternatives`: significant candidates of the round
    whose ΔBIC is within `INDISTINCT_BIC` of its own (the recording does not tell them
    apart); `equivalent`: the candidates of its round that, fitted in its place, Vuong's
    test on the held-out blocks does not find worse (equally supported), each with its
    z, the held-out χ² by which it is worse and the static poses that would tell the
    two apart (``{"effect", "heldout_z", "heldout_chi2_worse", "next_poses"}``)."""

    effect: str
    parameters: dict[str, tuple[float, float]]
    gap_after_m: float
    score: dict[str, Any]
    candidates: dict[str, dict[str, Any]]
    term: dict[str, Any] | None = None
    replaces: tuple[str, ...] = ()
    alternatives: tuple[str, ...] = ()
    equivalent: tuple[dict[str, Any], ...] = ()


@dataclasses.dataclass(frozen=True)
class Observations:
    """The recording as the search sees it, per observation `(N, M)` (frames, the
    recording's LED columns): the emission `angles` [rad], the per-axis variance `var`
    [m²] of the recording's `noise` model (`NoiseModel`), the fit `weights` 1/var
    [1/m²] (0 where unseen), the `variables` the structure test steers the search by,
    the `heldout` check over alternate time blocks, and the variables the gap is
    `localised` by (`variables` and the derived ones, `frame_variables`)."""

    rec: Recording
    angles: np.ndarray
    noise: NoiseModel
    var: np.ndarray
    weights: np.ndarray
    variables: dict[str, np.ndarray]
    heldout: HeldOut
    localised: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def sigma(self) -> float:
        """The RMS noise σ per axis over all observations [m]."""
        return float(np.sqrt(np.nanmean(self.var)))


def observations(rec: Recording) -> Observations:
    """Emission angles, the noise model and the weights of `rec`
    (`robtraj.estimate.observation_noise`), with the localisation variables."""
    angles = observation_angles(rec)
    noise, var = observation_noise(rec, angles)
    weights = np.where(rec.visible & np.isfinite(var), 1.0 / var, 0.0)
    return Observations(
        rec,
        angles,
        noise,
        var,
        weights,
        frame_variables(rec, angles),
        HeldOut(rec, weights, var),
        frame_variables(rec, angles, derived=True),
    )


@dataclasses.dataclass(frozen=True)
class Search:
    """What stays fixed while the search runs: the observations `obs`; the `nominal` fit
    (the effects `include`d from the start), whose LED order every later fit keeps, with
    3σ̂² `var3` [m²] and the weights `aligned_weights` [1/m²] `(N, M)` in that order and
    its number of residuals `n_obs`; the `candidates` to search, the space every fit
    shares (`shared`; None for a space per round), and `say`, which reports progress;
    `screened`: how many candidates a screen chose `candidates` from (constructed
    terms), the count the significance level is divided by when it exceeds theirs."""

    obs: Observations
    nominal: Any
    var3: np.ndarray
    aligned_weights: np.ndarray
    n_obs: int
    candidates: tuple[str, ...]
    include: tuple[str, ...]
    shared: tuple[str, ...] | None
    say: Callable[[str], None]
    screened: int = 0

    def gap(self, res) -> float:
        """The gap of the fit `res` [m], less the noise its parameters absorb."""
        return gap(res, self.var3, noise_share(res))

    def floor(self, res) -> float:
        """The gap the fit `res` reaches by chance with this noise and data [m]."""
        return gap_floor(res, self.var3, self.obs.noise.level_rel_se)

    def reported(self, res, estimate: tuple[str, ...], space: tuple[str, ...]):
        """The fit of `estimate` refitted from `res` with the cluster-robust σ: what a
        step reports."""
        from ..estimate.calibration import fit

        return fit(
            self.obs.rec, estimate=tuple(estimate), weights=self.obs.weights, init=res, space=space
        )


@dataclasses.dataclass(frozen=True)
class SearchState:
    """The model as the search stands: the effects `named` (those included first) and
    their fit `current` in the space `space`, whether that fit carries the cluster-robust
    σ (`robust`); the gap after each step [m] (`gaps`, the nominal fit's first) and the
    floor of the last [m]; the held-out gap of `current` [m] (None until a check needs
    it); the `steps` and `rejected` candidates so far; the effects dropped (`tried`), and
    why the search `stopped` ("" while it runs)."""

    named: tuple[str, ...]
    current: Any
    space: tuple[str, ...]
    robust: bool
    gaps: tuple[float, ...]
    floor: float
    heldout_gap: float | None = None
    steps: tuple[Step, ...] = ()
    rejected: tuple[dict[str, Any], ...] = ()
    tried: frozenset[str] = frozenset()
    stopped: str = ""


def start(
    obs: Observations,
    candidates: tuple[str, ...],
    include: tuple[str, ...],
    shared: tuple[str, ...] | None,
    say: Callable[[str], None],
) -> tuple[Search, SearchState]:
    """The nominal fit (with the effects `include`d) and the search's start from it."""
    from ..estimate.calibration import fit

    rec = obs.rec
    # search fits leave out the cluster-robust σ (a pass and a compilation of their own);
    # the fit a step reports is refitted with it (`Search.reported`)
    nominal = fit(
        rec, estimate=include, weights=obs.weights, space=shared or (), robust_sigma=False
    )
    search = Search(
        obs,
        nominal,
        aligned(rec, nominal, 3.0 * obs.var),
        aligned(rec, nominal, obs.weights),
        int(np.isfinite(nominal.residuals[..., 0]).sum()) * 3,
        candidates,
        include,
        shared,
        say,
    )
    state = SearchState(
        named=include,
        current=nominal,
        space=shared or (),
        robust=False,
        gaps=(search.gap(nominal),),
        floor=search.floor(nominal),
    )
    return search, state
