"""Joint-angle error maps: a periodic, piecewise-linear angle error of one joint.

``Δqⱼ = Σₖ cₖ φₖ(qⱼ)`` [rad], with φₖ the periodic hat function of knot k on a uniform
grid of `N_KNOTS` knots over one revolution (spacing ``h = 2π/N_KNOTS``): ``φₖ(q) =
max(0, 1 − |q − 2πk/N_KNOTS|/h)`` with the difference wrapped into [−π, π). The map
is 2π-periodic (the same output angle carries the same error whatever turn the joint
is on) and linear in its coefficients, which are the error at the knots [rad]. Each
angle lies between two knots, so only two features are non-zero: the fits accumulate
a map's normal equations from those two (`active`), never from a Jacobian with a
column per knot.

What such a map models: a transmission or angle-sensor error that repeats with the
joint angle at many cycles per revolution (a UR10's joints carry one of ~17 cycles per
revolution, ±0.5 mrad; `docs/real_ur10.md`), which a few harmonics cannot represent.
The coefficients get a zero-mean Gaussian prior (`precision`): a map has a parameter
per knot and is determined where the data are by the data, elsewhere by the prior.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

#: knots per revolution: h = 2π/256 = 0.0245 rad, ~15 knots per period of a 17-cycle
#: error (a linear interpolant of a sinusoid at 15 points per period is off by ≤ 2 % of
#: its amplitude); half the spacing did not predict held-out poses better on the UR10
N_KNOTS = 256
#: default prior: amplitude scale σ_f [rad] and correlation length ℓ [rad] (`precision`),
#: chosen by blocked cross-validation on both UR10 series (the pose workflow chooses its
#: own per series from `PRIOR_GRID`)
SIGMA_F = 3e-3
LENGTH = 0.05
#: the grid of (σ_f [rad], ℓ [rad]) the pose workflow's cross-validation chooses from
PRIOR_GRID = tuple((s, ell) for s in (1e-3, 3e-3, 1e-2) for ell in (0.025, 0.05, 0.1))


def spacing(n_knots: int = N_KNOTS) -> float:
    """Knot spacing h [rad]."""
    return 2.0 * math.pi / n_knots


def knots(n_knots: int = N_KNOTS) -> np.ndarray:
    """Knot angles [rad] in [0, 2π), `(n_knots,)`."""
    return np.arange(n_knots) * spacing(n_knots)


def active(q, n_knots: int = N_KNOTS):
    """The two non-zero features at joint angles `q` [rad] (any shape ``S``): knot
    indices `(*S, 2)` (the knot below and the one above, modulo `n_knots`) and their
    hat values `(*S, 2)`, which sum to 1. Works on NumPy and JAX arrays."""
    xp = jnp if isinstance(q, jnp.ndarray) else np
    x = xp.mod(q, 2.0 * math.pi) / spacing(n_knots)
    lo = xp.floor(x)
    u = x - lo
    i0 = lo.astype(xp.int32) % n_knots
    return xp.stack([i0, (i0 + 1) % n_knots], -1), xp.stack([1.0 - u, u], -1)


def features(q, n_knots: int = N_KNOTS):
    """Every hat feature at the angles `q` [rad] (JAX): `(*S, n_knots)`, zero but at the
    two knots around each angle (the dense form, for fits that take a term's features
    as one array)."""
    d = jnp.mod(q[..., None] - jnp.asarray(knots(n_knots), q.dtype) + math.pi, 2 * math.pi)
    return jnp.maximum(0.0, 1.0 - jnp.abs(d - math.pi) / spacing(n_knots))


def values(coefficients: np.ndarray, q: np.ndarray | float) -> np.ndarray | float:
    """The map [rad] with knot values `coefficients` `(n_knots,)` at angles `q` (NumPy)."""
    c = np.asarray(coefficients, float)
    idx, w = active(np.asarray(q, float), c.size)
    return np.sum(c[idx] * w, -1)


def precision(n_knots: int = N_KNOTS, sigma_f: float = SIGMA_F, length: float = LENGTH):
    """Precision matrix [1/rad²] of the coefficients' zero-mean Gaussian prior,
    ``Λ = (I + (ℓ/h)²/2 · DᵀD)/σ_f²`` with D the periodic first difference: the prior
    cost ``cᵀΛc`` is ``Σ cₖ²/σ_f² + (ℓ²/2σ_f²)·Σ ((cₖ₊₁ − cₖ)/h)²``, a discrete
    Sobolev prior that bounds the map's size (σ_f) and its slope (over lengths ℓ)."""
    h = spacing(n_knots)
    d = np.roll(np.eye(n_knots), 1, axis=1) - np.eye(n_knots)
    return (np.eye(n_knots) + (length / h) ** 2 / 2.0 * (d.T @ d)) / sigma_f**2


def support(q: np.ndarray, n_knots: int = N_KNOTS, margin: int = 8) -> np.ndarray:
    """`(n_knots,)` bool: knots whose hat function touches an angle of `q` [rad], widened
    by `margin` knots on each side. Further from the data the prior alone determines a
    knot (its posterior is its prior, mean zero): a fit may hold those at zero."""
    idx, _ = active(np.asarray(q, float), n_knots)
    touched = np.zeros(n_knots, bool)
    touched[idx.ravel()] = True
    out = touched.copy()
    for k in range(1, margin + 1):
        out |= np.roll(touched, k) | np.roll(touched, -k)
    return out


def summary(
    coefficients: np.ndarray, q_range: tuple[float, float] | None = None
) -> dict[str, float]:
    """What a map does, in numbers, over the knots inside `q_range` [rad] (where the data
    are; the whole revolution if None): RMS and peak [rad], and the frequency of its
    strongest periodic component [cycles per revolution] — the peak of the spectrum of
    the knots' values (mean and linear trend removed, Hann window, zero-padded), among
    frequencies that complete at least one cycle inside the range."""
    c = np.asarray(coefficients, float)
    n = c.size
    h = spacing(n)
    if q_range is None:
        lo, hi = -math.pi, math.pi
        x = c
        span = 2 * math.pi
    else:
        lo, hi = float(q_range[0]), float(q_range[1])
        span = min(hi - lo, 2 * math.pi)
        # the knots in the range, in order of angle from `lo` (one of each knot's turns)
        start = int(math.floor(lo / h))
        idx = np.arange(start, start + int(math.ceil(span / h)) + 1) % n
        x = c[idx]
    if q_range is None:
        y = x - x.mean()
    else:
        t = np.arange(x.size)
        y = x - np.polyval(np.polyfit(t, x, 1), t) if x.size > 2 else x - x.mean()
        y = y * np.hanning(x.size)
    n_fft = 1 << int(math.ceil(math.log2(max(16 * x.size, 4096))))
    spectrum = np.abs(np.fft.rfft(y, n_fft))
    cycles = np.fft.rfftfreq(n_fft, d=h) * 2 * math.pi  # cycles per revolution
    usable = cycles >= 2 * math.pi / span
    cpr = float(cycles[usable][np.argmax(spectrum[usable])]) if usable.any() else 0.0
    return {
        "rms_rad": float(np.sqrt(np.mean(x**2))),
        "peak_rad": float(np.max(np.abs(x))),
        "cycles_per_rev": cpr,
        "range_rad": (lo, hi),
    }


def words(joint: int, coefficients: np.ndarray, q_range: tuple[float, float] | None) -> str:
    """The map of joint `joint` (1-based) in words, e.g. ``joint 2 angle error map: rms
    0.31 mrad, peak 0.65 mrad, strongest at 17 cycles/rev, over q2 ∈ [−2.40, 0.10] rad
    (where the data are)`` (`summary`)."""
    s = summary(coefficients, q_range)
    lo, hi = s["range_rad"]
    where = "(where the data are)" if q_range is not None else "(one revolution)"
    return (
        f"joint {joint} angle error map: rms {s['rms_rad'] * 1e3:.2f} mrad, peak "
        f"{s['peak_rad'] * 1e3:.2f} mrad, strongest at {s['cycles_per_rev']:.0f} cycles/rev, "
        f"over q{joint} ∈ [{_signed(lo)}, {_signed(hi)}] rad {where}"
    )


def _signed(x: float) -> str:
    return f"{x:.2f}".replace("-", "−")
