"""The parameters of a bundle fit: the effects in its problem, the names of θ and of the
reported parameters, and which of them the model holds.

θ = [g, c]: g holds the camera←base and flange←tool corrections (jaxlie tangent order
``[tx, ty, tz, rx, ry, rz]``), then each effect of the problem entry by entry; c the
coefficients of the constellation basis (3 per LED, padded: fixed shapes). The reported
parameters (`CalibrationResult.parameter_names`) have the constellation's coordinates in
place of c.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .._errors import UserError
from ..model import (
    EFFECT_NAMES,
    LIBRARY,
    Effects,
    RobotModel,
    effect_component_names,
    is_effect,
    known_effects,
    redundant_link_parameters,
)

_TANGENT = ("tx", "ty", "tz", "rx", "ry", "rz")


def check_names(names) -> None:
    """`UserError` for a name that is no effect of the library or the dictionary (a
    constructed term's name is one: `is_effect` builds it)."""
    bad = [e for e in names if not is_effect(e)]
    if bad:
        raise UserError(
            f"unknown effect(s) {', '.join(bad)} (known: the library "
            f"{', '.join(LIBRARY)}, link_twist and the dictionary's terms)"
        )


def library_space(*extra: Sequence[str]) -> tuple[str, ...]:
    """The library (`robtraj.model.LIBRARY`) and the effects named in `extra`, in
    `EFFECT_NAMES` order: the problem space of the discrepancy search, shared by its
    fits, score tests and held-out predictions so that they compile once."""
    wanted = set(LIBRARY).union(*map(set, extra))
    return tuple(n for n in known_effects() if n in wanted)


def effects_in_problem(estimate, space) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The effects in the problem (`estimate` and `space`) and the estimated ones, each
    in `known_effects` order; `UserError` for an unknown name."""
    estimate = tuple(dict.fromkeys(estimate))
    check_names((*estimate, *space))
    order = known_effects()
    free = tuple(n for n in order if n in estimate or n in space)
    return free, tuple(n for n in order if n in estimate)


def dictionary_terms(free: tuple[str, ...]) -> tuple[str, ...]:
    """The dictionary's terms among the effects `free` (the library's are fields of
    `Effects`)."""
    return tuple(n for n in free if n not in EFFECT_NAMES)


def theta_names(effects: Effects, free: tuple[str, ...], n_leds: int) -> tuple[list[str], int]:
    """The names of θ and the number q of its global entries (g)."""
    names = [f"camera_from_base.{t}" for t in _TANGENT]
    names += [f"flange_from_tool.{t}" for t in _TANGENT]
    for name in free:
        names += effect_component_names(name, np.shape(effects.get(name)))
    q = len(names)
    return names + [f"constellation.c{j}" for j in range(3 * n_leds)], q


def effect_of(parameter: str) -> str:
    """The effect a parameter name belongs to: ``link_length[1].a`` → ``link_length``,
    ``joint1_harmonic2.sin`` → ``joint1_harmonic2``."""
    return parameter.partition("[")[0].partition(".")[0]


def in_model(names_theta, free, estimated, robot: RobotModel) -> np.ndarray:
    """θ entries of the model: the poses, the estimated effects (without the link
    parameters the kinematics make redundant) and the constellation; not the held
    effects."""
    held = set(free) - set(estimated)
    redundant = set(redundant_link_parameters(robot))
    return np.array([effect_of(n) not in held and n not in redundant for n in names_theta])


def droppable(names_theta, q: int) -> np.ndarray:
    """θ entries the identifiability analysis may fix: the effects'."""
    return np.array([12 <= i < q for i in range(len(names_theta))])


def has_column(q: int, basis: np.ndarray) -> np.ndarray:
    """θ entries that are parameters (not padding of the constellation basis)."""
    return np.concatenate([np.ones(q, bool), np.any(basis != 0, axis=0)])


def readable_names(names_theta, q: int, basis: np.ndarray, led_ids) -> list[str]:
    """Readable names for θ: constellation coefficients named by their dominant LED."""
    out = list(names_theta[:q])
    for j in range(basis.shape[1]):
        k = int(np.argmax(np.abs(basis[:, j])))
        out.append(f"constellation[LED {int(led_ids[k // 3])}].{'xyz'[k % 3]}")
    return out


def reported_names(names_theta, q: int, led_ids) -> list[str]:
    """The names of the reported parameters: g's, then each LED's coordinates."""
    return names_theta[:q] + [
        f"constellation[LED {int(i)}].{c}" for i in led_ids for c in ("x", "y", "z")
    ]
