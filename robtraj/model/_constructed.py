"""Constructed terms: a joint angle error built from the recording's signals.

A constructed term adds ``Δqⱼ = Σₖ cₖ φₖ`` to joint j's angle [rad], with φ the products
of the basis functions of one or two *factors*, each a function of one signal of the
frame:

- ``q{i}`` — joint i's logged angle [rad] (a linear function: an error per radian of
  qᵢ);
- ``q{i}h{h}`` — the sine and cosine of h times joint i's angle (a harmonic of it);
- ``tau{i}`` — joint i's gravity torque [N·m] (a deflection driven by it).

Its name is its definition: ``joint2_by_q3h3_q4h1`` is joint 2's angle error as the four
products ``{sin, cos}(3·q3) · {sin, cos}(q4)``; ``joint3_by_q2`` is joint 3's error per
radian of q2. So a named model that holds one is read back from CALIB.json without
anything registered (`term` builds it from its name), and the discrepancy search can
offer any of them (`candidate_groups`) without a fixed list. Like every dictionary term
they are linear in their coefficients and go through the one forward model
(`robtraj.model.effective_joints`).
"""

from __future__ import annotations

import dataclasses
import itertools
import re

import jax.numpy as jnp

#: harmonics of a joint angle a factor takes [cycles per revolution]
FACTOR_HARMONICS = (1, 2, 3)
_FACTOR = r"(?:q\d+(?:h\d+)?|tau\d+)"
_NAME = re.compile(rf"^joint(\d+)_by_({_FACTOR})(?:_({_FACTOR}))?$")


@dataclasses.dataclass(frozen=True)
class Factor:
    """One signal's basis functions: `signal` ``"q"`` (joint angle) or ``"tau"`` (gravity
    torque) of joint `joint` (0-based); `harmonic` h > 0: ``sin(h·q), cos(h·q)``, else the
    signal itself."""

    signal: str
    joint: int
    harmonic: int = 0

    @property
    def name(self) -> str:
        h = f"h{self.harmonic}" if self.harmonic else ""
        return f"{self.signal}{self.joint + 1}{h}"

    @property
    def components(self) -> tuple[str, ...]:
        v = f"{self.signal}{self.joint + 1}"
        if self.harmonic:
            return (f"sin{self.harmonic}{v}", f"cos{self.harmonic}{v}")
        return (v,)

    @property
    def unit(self) -> str:
        """The unit of the factor's values ("" when dimensionless)."""
        if self.harmonic:
            return ""
        return "rad" if self.signal == "q" else "N·m"

    @property
    def words(self) -> tuple[str, ...]:
        """Each basis function in words (``"sin(3·q3)"``, ``"q2"``)."""
        v = f"{'q' if self.signal == 'q' else 'τ'}{self.joint + 1}"
        if self.harmonic:
            arg = v if self.harmonic == 1 else f"{self.harmonic}·{v}"
            return (f"sin({arg})", f"cos({arg})")
        return (v,)

    def values(self, q, tau, xp=jnp):
        """The basis functions `(..., k)` at joint angles `q` [rad] and gravity torques
        `tau` [N·m], each `(..., joints)`."""
        x = (q if self.signal == "q" else tau)[..., self.joint]
        if self.harmonic:
            return xp.stack([xp.sin(self.harmonic * x), xp.cos(self.harmonic * x)], -1)
        return x[..., None]


def _factor(text: str) -> Factor:
    m = re.fullmatch(r"(q|tau)(\d+)(?:h(\d+))?", text)
    return Factor(m[1], int(m[2]) - 1, int(m[3] or 0))


def parse(name: str) -> tuple[int, tuple[Factor, ...]] | None:
    """``(joint (0-based), factors)`` of a constructed term's name; None for any other."""
    m = _NAME.match(name)
    if m is None:
        return None
    factors = tuple(_factor(f) for f in m.groups()[1:] if f is not None)
    if int(m[1]) < 1 or any(f.joint < 0 for f in factors):
        return None
    if len(factors) == 2 and factors[0].signal == factors[1].signal:
        if factors[0].joint == factors[1].joint:
            return None
    return int(m[1]) - 1, factors


def name_of(joint: int, factors: tuple[Factor, ...]) -> str:
    """The name of joint `joint`'s (0-based) constructed term of `factors`."""
    return f"joint{joint + 1}_by_" + "_".join(f.name for f in factors)


def features(factors: tuple[Factor, ...], q, tau, xp=jnp):
    """The products of the factors' basis functions `(..., k)`, the first factor's index
    running slowest (the order of `components`)."""
    out = factors[0].values(q, tau, xp)
    for f in factors[1:]:
        v = f.values(q, tau, xp)
        out = (out[..., :, None] * v[..., None, :]).reshape(*out.shape[:-1], -1)
    return out


def components(factors: tuple[Factor, ...]) -> tuple[str, ...]:
    """Coefficient names: the factors' component names joined by ``_``."""
    return tuple("_".join(c) for c in itertools.product(*(f.components for f in factors)))


def function_words(factors: tuple[Factor, ...]) -> tuple[str, ...]:
    """Each product of basis functions in words (``"cos(3·q3)·sin(q4)"``)."""
    return tuple("·".join(w) for w in itertools.product(*(f.words for f in factors)))


def unit(factors: tuple[Factor, ...]) -> str:
    """The coefficients' unit: rad of joint angle error per unit of the product."""
    per = "·".join(f.unit for f in factors if f.unit)
    return f"rad/({per})" if per else "rad"


def candidate_groups(n_joints: int) -> list[tuple[int, tuple[Factor, ...]]]:
    """Every constructed term the discrepancy search screens for a robot of `n_joints`
    joints, as ``(joint, factors)``: per joint j, each factor alone and each product of
    two factors of different signals, leaving out those the dictionary and the library
    hold already (harmonics of qⱼ itself, in the dictionary up to 4 cycles; τⱼ alone,
    the joint compliance)."""
    angle = [Factor("q", i, h) for i in range(n_joints) for h in (0, *FACTOR_HARMONICS)]
    torque = [Factor("tau", i) for i in range(n_joints)]
    every = angle + torque
    out = []
    for j in range(n_joints):
        for f in every:
            if (f.signal == "q" and f.joint == j and f.harmonic) or (
                f.signal == "tau" and f.joint == j
            ):
                continue
            out.append((j, (f,)))
        for a, b in itertools.combinations(every, 2):
            if (a.signal, a.joint) != (b.signal, b.joint):
                out.append((j, (a, b)))
    return out
