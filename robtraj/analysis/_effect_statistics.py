"""What a calibration fit says of one effect: its free parameters with value and σ, the
fit with it set to zero, and the χ² test (p-value and ΔBIC) of a likelihood ratio or
score statistic."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy import stats

from ..model import term


def _of_effect(name: str, effect: str) -> bool:
    return name == effect or name.startswith(effect + "[") or name.startswith(effect + ".")


def effect_parameters(res, effect: str) -> dict[str, tuple[float, float]]:
    """{parameter name: (value, σ)} (SI units) of `effect` in the fit `res`, without those
    the fit held fixed (not identifiable)."""
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


def free_count(res, effect: str) -> int:
    """How many parameters of `effect` the fit `res` estimated."""
    return len(effect_parameters(res, effect))


def significance(value: float, dof: int, n_obs: int, **extra) -> dict[str, Any]:
    """`extra` with the `dof`, the χ²(dof) `p_value` of the statistic `value` and its
    `delta_bic` (value − dof · ln `n_obs`, the BIC decrease of the `dof` parameters)."""
    return {
        **extra,
        "dof": dof,
        "p_value": float(stats.chi2.sf(max(value, 0.0), dof)),
        "delta_bic": float(value - dof * np.log(n_obs)),
    }


def without(res, effect: str):
    """`res` with `effect` set to zero (the start of a refit that leaves it out)."""
    eff = dict(res.effects)
    eff[effect] = np.zeros_like(np.asarray(eff[effect], float)).tolist()
    return dataclasses.replace(res, effects=eff)
