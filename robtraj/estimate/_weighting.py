"""Weighting schemes: pure, jit-able functions from per-LED features to weights.

A scheme takes an `LedFeatures` and keyword parameters and returns `(frames, leds)`
non-negative weights, zero where an LED is not seen. Users add their own with
`register_weighting`.

The pose pipeline passes over a recording in chunks of frames, and calls a scheme on
one chunk at a time (all LEDs of each frame): a scheme must treat the frames
independently (reduce over the LED axis only). What needs the whole recording comes as
a recording-level feature (``residual_scale``), computed in a pass of its own.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._errors import UserError


class LedFeatures(eqx.Module):
    """What a weighting scheme may look at, per frame and LED.

    - `visible`: LED seen.
    - `variance` [m²]: the paper's LED variance (eq. 3–5), NaN when too few frames.
    - `pairwise_variance` [m²]: mean windowed variance of the pair distances.
    - `residual` [m]: distance of the LED from a previous fit (0 before any fit).
    - `emission_angle` [rad]: angle to the camera from known normals (NaN if unknown).
    - `noise_variance` [m²]: per-axis variance of the observation under the recording's
      noise model (`robtraj.estimate.estimate_noise`: emission angle, distance, LED).
    - `residual_scale` [m], recording-level: 1.4826 × the median absolute `residual` of
      the seen LEDs over the whole recording (a robust σ); None where not computed.
    """

    visible: Bool[Array, "frames leds"]
    variance: Float[Array, "frames leds"]
    pairwise_variance: Float[Array, "frames leds"]
    residual: Float[Array, "frames leds"]
    emission_angle: Float[Array, "frames leds"]
    noise_variance: Float[Array, "frames leds"]
    residual_scale: Float[Array, ""] | None = None


WeightingFn = Callable[..., Float[Array, "frames leds"]]
_REGISTRY: dict[str, WeightingFn] = {}
_NEEDS: dict[str, frozenset[str]] = {}
FEATURES = frozenset(
    {
        "variance",
        "pairwise_variance",
        "residual",
        "emission_angle",
        "noise_variance",
        "residual_scale",
    }
)


def register_weighting(name: str, fn: WeightingFn | None = None, *, needs=("variance",)):
    """Register `fn(features, **params) -> weights` under `name` (usable as a decorator).

    `needs` names the `LedFeatures` fields the scheme reads beyond `visible`; the pose
    pipeline computes only those (``residual``, ``emission_angle``, ``noise_variance``
    and ``residual_scale`` come from a previous fit, so such schemes are iterated). The
    pipeline calls `fn` on chunks of frames: it must treat frames independently (see the
    module docstring).
    """
    unknown = set(needs) - FEATURES
    if unknown:
        raise ValueError(f"unknown features {sorted(unknown)}; choose from {sorted(FEATURES)}")

    def add(f: WeightingFn) -> WeightingFn:
        _REGISTRY[name] = f
        _NEEDS[name] = frozenset(needs)
        return f

    return add if fn is None else add(fn)


def weighting_needs(name: str) -> frozenset[str]:
    """The features scheme `name` reads."""
    get_weighting(name)
    return _NEEDS[name]


def weighting_schemes() -> list[str]:
    return sorted(_REGISTRY)


def get_weighting(name: str) -> WeightingFn:
    if name not in _REGISTRY:
        raise UserError(f"unknown weighting {name!r} (known: {', '.join(weighting_schemes())})")
    return _REGISTRY[name]


def _inverse(v, visible, floor_fraction):
    """1/v with a floor at `floor_fraction` × the frame's median variance; unknown v → the
    frame's median (an LED just appeared is neither trusted nor discarded)."""
    v = jnp.where(visible & jnp.isfinite(v), v, jnp.nan)
    med = jnp.nanmedian(v, axis=1, keepdims=True)
    med = jnp.where(jnp.isfinite(med), med, 1.0)
    v = jnp.where(jnp.isfinite(v), v, med)
    v = jnp.maximum(v, floor_fraction * med)
    return jnp.where(visible, 1.0 / v, 0.0)


@register_weighting("uniform", needs=())
def uniform(f: LedFeatures) -> Float[Array, "frames leds"]:
    """Every seen LED counts the same."""
    return f.visible.astype(f.variance.dtype)


@register_weighting("inverse_variance")
def inverse_variance(f: LedFeatures, floor_fraction: float = 0.05) -> Float[Array, "frames leds"]:
    """The paper's weighting: 1 / LED variance (eq. 3–5)."""
    return _inverse(f.variance, f.visible, floor_fraction)


@register_weighting("pairwise_inverse_variance", needs=("pairwise_variance",))
def pairwise_inverse_variance(
    f: LedFeatures, floor_fraction: float = 0.05
) -> Float[Array, "frames leds"]:
    """1 / pairwise LED variance (does not jump when partners appear or vanish)."""
    return _inverse(f.pairwise_variance, f.visible, floor_fraction)


@register_weighting("led_noise", needs=("pairwise_variance",))
def led_noise(f: LedFeatures, floor_fraction: float = 0.05) -> Float[Array, "frames leds"]:
    """1 / the LED's own noise variance, separated from its partners' noise.

    A pair distance varies by both LEDs' noise, ``V_ab = s_a + s_b`` (per-axis
    variances projected on the pair), so the pairwise LED variance is
    ``s_a + mean(s_partners)`` and ``s_a ≈ V̄_a − ½·mean_frame(V̄)``. Unlike the paper's
    variance it neither mixes in the partners' noise nor jumps when they appear or
    vanish: on simulated data it comes within a few per cent of the Cramér–Rao bound.
    """
    pv = jnp.where(f.visible & jnp.isfinite(f.pairwise_variance), f.pairwise_variance, jnp.nan)
    s = pv - 0.5 * jnp.nanmean(pv, axis=1, keepdims=True)
    med = jnp.nanmedian(s, axis=1, keepdims=True)
    med = jnp.where(jnp.isfinite(med) & (med > 0), med, 1.0)
    s = jnp.where(jnp.isfinite(s), s, med)
    s = jnp.maximum(s, floor_fraction * med)
    return jnp.where(f.visible, 1.0 / s, 0.0)


@register_weighting("threshold")
def threshold(f: LedFeatures, factor: float = 3.0) -> Float[Array, "frames leds"]:
    """Uniform, but LEDs whose variance exceeds `factor` × the frame median are dropped."""
    v = jnp.where(f.visible & jnp.isfinite(f.variance), f.variance, jnp.nan)
    med = jnp.nanmedian(v, axis=1, keepdims=True)
    keep = f.visible & ~(v > factor * med)
    return keep.astype(f.variance.dtype)


@register_weighting("robust", needs=("residual", "residual_scale"))
def robust(f: LedFeatures, k: float = 1.345, scale: float | None = None):
    """Huber IRLS weights from the residual of a previous fit: 1 inside k·σ, k·σ/|r| outside.

    σ is `scale` [m] or 1.4826 × the median absolute residual of the seen LEDs over the
    recording (`f.residual_scale`; where that is None, over the frames of `f`).
    """
    r = jnp.where(f.visible, f.residual, jnp.nan)
    if scale is not None:
        s = scale
    elif f.residual_scale is not None:
        s = f.residual_scale
    else:
        s = 1.4826 * jnp.nanmedian(jnp.abs(r))
    s = jnp.where(s > 0, s, 1.0)
    a = jnp.abs(jnp.where(f.visible, f.residual, 0.0)) / s
    w = jnp.where(a <= k, 1.0, k / jnp.maximum(a, k))
    return jnp.where(f.visible, w, 0.0)


@register_weighting("emission_angle", needs=("noise_variance",))
def emission_angle_weight(f: LedFeatures, floor_fraction: float = 0.05):
    """1/σ² of the recording's noise model, which grows with the emission angle and the
    distance and differs from LED to LED (estimated from the recording itself; without
    LED normals, of distance and LED only)."""
    return _inverse(f.noise_variance, f.visible, floor_fraction)
