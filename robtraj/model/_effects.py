"""The effect library of DESIGN section 7: what the nominal model leaves out.

Every effect is a field of one `Effects` module; all zeros is the nominal model. The
simulator generates with it and the estimators fit it, through the one forward model
in `_measurement.py`.
"""

from __future__ import annotations

import dataclasses
import json

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._errors import UserError
from ._dictionary import reserve, term as _term, term_names

#: emission angle [rad] at which `led_angle_bias` is quoted
BIAS_REFERENCE_ANGLE = float(np.deg2rad(60.0))


class Effects(eqx.Module):
    """Physical effects, each zero in the nominal model (SI units).

    - `time_offset` [s]: robot clock minus tracker clock (τ); the tracker frame at
      tracker time t sees the robot at robot time t + τ.
    - `joint_offset` `(joints,)` [rad]: zero-position error added to each joint.
    - `link_length` `(joints, 2)` [m]: errors of the DH lengths ``[Δd, Δa]``.
    - `link_twist` `(joints, 2)` [rad]: errors of the link's axis direction ``[Δα, Δβ]``:
      Δα of the DH twist (about xᵢ) and Hayati's Δβ, a turn of frame i about its own
      yᵢ (the link transform becomes ``… · Rx(α + Δα) · Ry(Δβ)``). Δβ is what tilts a
      joint axis parallel to the previous one; where consecutive axes are not parallel
      the DH parameters already cover it, and it is not estimated there, nor the last
      link's axis direction (`redundant_link_parameters`).
    - `joint_compliance` `(joints,)` [rad/(N·m)]: deflection = compliance · gravity torque.
    - `backlash` `(joints,)` [rad]: offset of sign equal to the joint's direction of
      motion (the last direction is held while the joint stands still).
    - `led_angle_bias` [m]: LED position bias along its emission axis, quoted at an
      emission angle of 60°, growing as ``(1 − cos θ)/(1 − cos 60°)``.
    - `tracker_scale` [1]: the tracker measures ``(1 + s)`` times the true coordinates.
    - `thermal_drift` `(3,)` [m/K]: translation of camera←base per kelvin of camera
      temperature change since the first frame (per minute of time when the recording
      has no temperature).
    - `terms` {name: `(k,)`}: coefficients of dictionary terms (`robtraj.model.term`),
      only those in use; a term that is absent is zero.
    """

    time_offset: Float[Array, ""]
    joint_offset: Float[Array, " joints"]
    link_length: Float[Array, "joints 2"]
    link_twist: Float[Array, "joints 2"]
    joint_compliance: Float[Array, " joints"]
    backlash: Float[Array, " joints"]
    led_angle_bias: Float[Array, ""]
    tracker_scale: Float[Array, ""]
    thermal_drift: Float[Array, "3"]
    terms: dict[str, Float[Array, " k"]]

    @classmethod
    def zeros(cls, n_joints: int = 6, terms: tuple[str, ...] = ()) -> Effects:
        """The nominal model, with zero coefficients for the dictionary `terms`."""
        z = jnp.zeros(n_joints)
        return cls(
            time_offset=jnp.zeros(()),
            joint_offset=z,
            link_length=jnp.zeros((n_joints, 2)),
            link_twist=jnp.zeros((n_joints, 2)),
            joint_compliance=z,
            backlash=z,
            led_angle_bias=jnp.zeros(()),
            tracker_scale=jnp.zeros(()),
            thermal_drift=jnp.zeros(3),
            terms={n: jnp.zeros(_term(n).size) for n in terms},
        )

    def get(self, name: str) -> Array:
        """The value of effect `name` (a library field or a dictionary term)."""
        if name in EFFECT_NAMES:
            return getattr(self, name)
        if name in self.terms:
            return self.terms[name]
        return jnp.zeros(_term(name).size)

    def replace(self, name: str, value: Array) -> Effects:
        """A copy with effect `name` set to `value` (traceable; shapes as `get`)."""
        if name in EFFECT_NAMES:
            return eqx.tree_at(lambda e: getattr(e, name), self, value)
        return eqx.tree_at(lambda e: e.terms, self, {**self.terms, name: value})

    def to_dict(self) -> dict[str, float | list]:
        """Non-zero effects as plain JSON-able values."""
        out = {}
        for name in (*EFFECT_NAMES, *self.terms):
            v = np.asarray(self.get(name))
            if np.any(v != 0):
                out[name] = v.tolist()
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, values: dict, n_joints: int = 6) -> Effects:
        eff = cls.zeros(n_joints, tuple(n for n in values if n not in EFFECT_NAMES))
        for name, v in values.items():
            eff = eff.with_value(name, v)
        return eff

    def with_value(self, name: str, value) -> Effects:
        """A copy with effect `name` set; a scalar for a per-joint effect fills all joints."""
        if name not in EFFECT_NAMES and _term(name) is None:
            raise UserError(f"unknown effect {name!r} (known: {', '.join(known_effects())})")
        old = self.get(name)
        try:
            new = jnp.broadcast_to(jnp.asarray(value, jnp.float64), old.shape)
        except ValueError:
            raise UserError(f"effect {name} takes {old.size} values, got {np.size(value)}")
        return self.replace(name, new)


EFFECT_NAMES = tuple(f.name for f in dataclasses.fields(Effects) if f.name != "terms")
reserve(EFFECT_NAMES)


def known_effects() -> tuple[str, ...]:
    """Every effect name the model knows: the library fields and the dictionary's terms."""
    return (*EFFECT_NAMES, *term_names())


def is_effect(name: str) -> bool:
    return name in EFFECT_NAMES or _term(name) is not None


#: the effect library of DESIGN section 7 that the discrepancy search scores by default
#: (`link_twist` is fitted when asked for; the pose-level workflow tries it)
LIBRARY = tuple(n for n in EFFECT_NAMES if n != "link_twist")
#: names of the two columns of the per-joint ``(joints, 2)`` effects
_ROW_COMPONENTS = {"link_length": ("d", "a"), "link_twist": ("alpha", "beta")}


def effect_component_names(name: str, shape: tuple[int, ...]) -> list[str]:
    """Parameter names of the entries of effect `name` of `shape`, in ``ravel`` order:
    ``time_offset``, ``joint_offset[2]``, ``link_length[1].a``, ``link_twist[2].beta``."""
    if shape == ():
        return [name]
    if _term(name) is not None:
        return [f"{name}.{c}" for c in _term(name).components]
    if name in _ROW_COMPONENTS:
        return [f"{name}[{j}].{c}" for j in range(shape[0]) for c in _ROW_COMPONENTS[name]]
    return [f"{name}[{j}]" for j in range(int(np.prod(shape)))]


def parse_effect(spec: str, n_joints: int = 6) -> tuple[str, np.ndarray]:
    """Parse ``NAME=VALUE`` (VALUE a number or comma-separated list) for `--effect`."""
    name, sep, value = spec.partition("=")
    name = name.strip()
    if not sep or not is_effect(name):
        raise UserError(
            f"bad --effect {spec!r}: expected NAME=VALUE with NAME one of "
            f"{', '.join(EFFECT_NAMES)} or a dictionary term (robtraj.model.dictionary)"
        )
    try:
        values = np.array([float(v) for v in value.split(",")])
    except ValueError:
        raise UserError(f"bad --effect {spec!r}: VALUE must be a number or comma-separated numbers")
    shape = np.shape(Effects.zeros(n_joints).get(name))
    try:
        if values.size == int(np.prod(shape)) and values.size > 1:
            values = values.reshape(shape)  # row-major: per joint, its components
        values = np.broadcast_to(values if values.size > 1 else values[0], shape)
    except ValueError:
        raise UserError(f"bad --effect {spec!r}: {name} takes 1 or {int(np.prod(shape))} values")
    return name, np.array(values)
