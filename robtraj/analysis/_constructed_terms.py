"""The screen of the constructed terms (`robtraj.model._constructed`): every joint angle
error built from one or two of the recording's signals, scored at once on the fit's
per-frame moments, so that only the strongest few reach the refits.

Per frame, the fit's residual is reduced once to its moments along each joint's angle
(`_gap_localisation.unit_moments`: ``Σ w CⱼᵀCⱼ``, ``Σ w Cⱼᵀr`` and the cross terms
with the nuisance — camera←base, flange←tool, the fit's estimated effects — with C the
observations' displacement per radian of joint j). A term of features φ on joint j
then has the Gauss–Newton predicted χ² decrease of the linearised refit with the
nuisance and every joint's constant offset (Rao's score statistic),
``sᵀS⁺s`` with ``S = Σ hφφᵀ − H_fe H_ee⁺ H_ef`` and ``s = Σ bφ − H_fe H_ee⁺ r_e``:
one product per term of its few columns, not a refit. The screen only proposes: what
it offers is tested like every candidate (`_discovery_steps`: the score test on the
whole recording, the refit's likelihood ratio, the held-out blocks), at the
significance of everything screened.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..estimate import covariance
from ..model import (
    constructed_features as features,
    constructed_groups as candidate_groups,
    constructed_name as name_of,
)
from ._effect_statistics import significance
from ._gap_localisation import unit_moments
from ._term_report import _term_inputs

#: constructed terms the screen offers to the refits per round, the strongest first
OFFERED = 3


@dataclasses.dataclass(frozen=True)
class Screened:
    """The screen's outcome: the terms `offered` (names, the strongest first), how many
    were `screened` (the count a significance level is divided by) and the screen's
    statistic of each offered one (χ² units, on the frames it used)."""

    offered: tuple[str, ...]
    screened: int
    statistics: dict[str, float]


def screen(search, state, exclude=frozenset()) -> Screened:
    """Score every constructed term of the recording's robot on the fit `state.current`
    (a `SearchState` of `search`), leaving out those named in `exclude`; offer the
    `OFFERED` of the largest ΔBIC > 0."""
    obs, res = search.obs, state.current
    um = unit_moments(
        obs.rec,
        res,
        res.residuals,
        search.aligned_weights,
        search.var3,
        obs.heldout.block,
        space=state.space,
        per_observation=False,
    )
    q, _, tau = _term_inputs(obs.rec, res.time_offset, res.motion_threshold)
    q, tau = np.asarray(q)[um.frames], np.asarray(tau)[um.frames]
    groups = [(j, f) for j, f in candidate_groups(q.shape[1]) if name_of(j, f) not in exclude]
    n_obs = 3 * int(um.use.sum())
    stats = _statistics(um.per_frame, groups, q, tau)
    ranked = sorted(
        (
            (significance(s, k, n_obs)["delta_bic"], name_of(j, f), s)
            for (j, f), (s, k) in zip(groups, stats)
            if k > 0
        ),
        reverse=True,
    )
    top = [(name, s) for d, name, s in ranked[:OFFERED] if d > 0]
    return Screened(tuple(n for n, _ in top), len(groups), dict(top))


def _statistics(mom, groups, q: np.ndarray, tau: np.ndarray) -> list[tuple[float, int]]:
    """`(statistic, rank)` of each group ``(joint, factors)`` on the per-frame moments
    `mom` (channels: 3 camera axes, then the joints), q and τ `(U, joints)` of its units;
    pseudo-inverses as the engine takes them (`robtraj.estimate.covariance`: column-scaled,
    null directions left out)."""
    # the nuisance with every joint's constant offset: its own products and residual
    nw_joint = mom.nw[:, :, 3:].sum(0)  # (g, J)
    hee = np.block([[mom.nnw.sum(0), nw_joint], [nw_joint.T, mom.gw[:, 3:, 3:].sum(0)]])
    re = np.concatenate([mom.nrw.sum(0), mom.bw[:, 3:].sum(0)])
    hee_inv, _ = covariance(hee, np.ones(len(hee), bool))
    cache: dict = {}
    out = []
    for j, factors in groups:
        c = 3 + j
        if factors not in cache:
            cache[factors] = features(factors, q, tau, np)
        phi = cache[factors]  # (U, k)
        h = mom.gw[:, c, c]
        cross = np.concatenate([mom.nw[:, :, c], mom.gw[:, 3:, c]], 1)  # (U, e)
        hfe = phi.T @ cross
        t = hfe @ hee_inv
        s = phi.T @ mom.bw[:, c] - t @ re
        schur = phi.T @ (h[:, None] * phi) - t @ hfe.T
        inv, rank = covariance(schur, np.ones(len(schur), bool))
        out.append((max(float(s @ inv @ s), 0.0), rank))
    return out
