"""Physics the simulator can add that robtraj's forward model does not know.

Each is written here in numpy, independently of `robtraj.model` (neither the effect
library nor the dictionary), so that a recording carrying one tests whether the
discrepancy search finds and names it rather than reproducing its own formulas. A joint
effect changes what the controller logs (the tracker sees the true arm); an LED effect
changes what the tracker measures.
"""

from __future__ import annotations

import dataclasses

import numpy as np

_U_REF = 1.0 - np.cos(np.deg2rad(60.0))


@dataclasses.dataclass(frozen=True)
class PeriodicJointError:
    """The encoder of `joint` (1-based) is off by ``amplitude·sin(cycles·q + phase)``
    [rad] (an eccentric or a transmission error): the controller logs the true angle
    minus it."""

    joint: int
    cycles: int
    amplitude: float
    phase: float = 0.0

    def log(self, time: np.ndarray, joints: np.ndarray) -> np.ndarray:
        out = joints.copy()
        q = joints[:, self.joint - 1]
        out[:, self.joint - 1] = q - self.amplitude * np.sin(self.cycles * q + self.phase)
        return out


_FACTORS = {"sin": np.sin, "cos": np.cos}


@dataclasses.dataclass(frozen=True)
class CrossJointError:
    """The encoder of `joint` (1-based) is off by ``amplitude·Π f(c·q_of)`` [rad], one
    factor per ``(f, c, of)`` of `factors`: f ``"sin"`` or ``"cos"``, c cycles per
    revolution, `of` the 1-based joint whose true angle [rad] it reads (a cable carrier
    or dress pack pulling one axis as others turn, a coupled transmission). The
    controller logs the true angle minus it."""

    joint: int
    amplitude: float
    factors: tuple[tuple[str, int | float, int], ...]

    def __post_init__(self):
        bad = [f for f, _, _ in self.factors if f not in _FACTORS]
        if bad or not self.factors:
            raise ValueError(
                f"factors must be (sin|cos, cycles, joint) triples, got {self.factors}"
            )

    def log(self, time: np.ndarray, joints: np.ndarray) -> np.ndarray:
        error = np.full(joints.shape[0], self.amplitude)
        for f, cycles, of in self.factors:
            error = error * _FACTORS[f](cycles * joints[:, of - 1])
        out = joints.copy()
        out[:, self.joint - 1] -= error
        return out


def joint_harmonics(
    seed: int, amplitude: float, joints: int = 6, cycles: tuple[int, ...] = (1, 2, 3)
) -> list[PeriodicJointError]:
    """A smooth error of every joint's angle: per joint, one `PeriodicJointError` per
    harmonic c of `cycles` with amplitude ``u·amplitude/c`` [rad], u uniform in [0.5, 1],
    and a uniform random phase (seeded). With `amplitude` 1e-4 rad, 0.04–0.18 mm RMS at
    the flange over the ``calibration`` scenario's poses."""
    rng = np.random.default_rng(seed)
    return [
        PeriodicJointError(j, c, amplitude * rng.uniform(0.5, 1.0) / c, rng.uniform(0, 2 * np.pi))
        for j in range(1, joints + 1)
        for c in cycles
    ]


@dataclasses.dataclass(frozen=True)
class VelocityDeadbandError:
    """Joint `joint` (1-based) trails its logged angle by ``amplitude`` [rad] against the
    direction of motion while it turns faster than `deadband` [rad/s], and not at all
    slower (friction wind-up that relaxes at rest; backlash, by contrast, holds)."""

    joint: int
    amplitude: float
    deadband: float = 0.02

    def log(self, time: np.ndarray, joints: np.ndarray) -> np.ndarray:
        out = joints.copy()
        v = np.gradient(joints[:, self.joint - 1], time)
        out[:, self.joint - 1] -= self.amplitude * np.sign(v) * (np.abs(v) > self.deadband)
        return out


@dataclasses.dataclass(frozen=True)
class SightLineBias:
    """Each LED is measured `amplitude` [m] too far along the line of sight from the
    camera at 60° emission angle, as ``(1 − cos θ)/(1 − cos 60°)`` (a spot centroid
    shifted by the LED's package, seen in depth)."""

    amplitude: float

    def leds(self, leds: np.ndarray, theta: np.ndarray) -> np.ndarray:
        sight = leds / np.linalg.norm(leds, axis=-1, keepdims=True)
        return leds + (self.amplitude * (1.0 - np.cos(theta)) / _U_REF)[..., None] * sight


def describe(effects) -> list[dict]:
    """JSON-able descriptions of unmodelled effects (for the truth)."""
    return [
        {"kind": type(e).__name__, **(dataclasses.asdict(e) if dataclasses.is_dataclass(e) else {})}
        for e in effects
    ]
