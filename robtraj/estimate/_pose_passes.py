"""The pose passes over a recording's frames behind `estimate_poses` (DESIGN 5.3).

A pose pass reads the LED positions chunk by chunk (with half a window of halo where the
LED variance is needed) and runs one jit-compiled kernel per chunk: the chunk's features
(LED variances, residuals and emission angles from the previous pass's poses, the noise
model's variance) → weights → weighted Procrustes. Only the per-frame fit stays in
memory. A statistic over the whole recording that a pass needs (the noise model, the
median residual) comes from passes of its own over the previous fit
(`_pose_statistics`); registration reads the static frames only (`_static_pieces`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from ..jax_ops import led_variances, rotation_rows, weighted_procrustes
from ..recording import FrameArray
from ._chunks import CHUNK, chunk_length, over_chunks, slab
from ._noise import NoiseModel, _observation_variance
from ._weighting import LedFeatures, get_weighting

_FIT_FIELDS = ("quaternion_wxyz", "position", "rms", "n_used", "valid")


@dataclasses.dataclass(frozen=True)
class PoseArrays:
    """The per-frame result of a pose pass (NumPy, as `RigidFit` without `condition`)."""

    quaternion_wxyz: np.ndarray
    position: np.ndarray
    rms: np.ndarray
    n_used: np.ndarray
    valid: np.ndarray


@dataclasses.dataclass(frozen=True)
class NoiseInputs:
    """What a pose pass needs for the ``noise_variance`` feature: the recording's noise
    `model`, the `fit` whose emission angles enter it, and the angle `fill` [rad] of an
    observation without one (no angles at all without `has_angle`)."""

    model: NoiseModel
    fit: PoseArrays
    fill: float
    has_angle: bool


class _Collect:
    """`over_chunks`' collector of per-frame results into preallocated arrays."""

    def __init__(self, n: int, size: int, fields: tuple[str, ...], advance: Callable) -> None:
        self.n, self.size, self.fields, self.advance = n, size, fields, advance
        self.out: dict[str, np.ndarray] = {}
        self.treedef = None

    def __call__(self, a: int, result) -> None:
        b = min(self.n, a + self.size)
        self.treedef = jax.tree.structure(result)
        for f in self.fields:
            v = np.asarray(getattr(result, f))
            if f not in self.out:
                self.out[f] = np.empty((self.n, *v.shape[1:]), v.dtype)
            self.out[f][a:b] = v[: b - a]
        self.advance(b - a)

    def rigid_fit(self):
        """The collected arrays as the chunks' result type (e.g. `RigidFit`), all its
        fields collected (the leaves in field order; no type check of NumPy leaves)."""
        return jax.tree.unflatten(self.treedef, [self.out[f] for f in self.fields])


def collect_fit(n: int, size: int, advance: Callable, fields=_FIT_FIELDS) -> _Collect:
    """A collector of the `fields` of the chunks' `RigidFit`s (`over_chunks`): in ``.out``,
    or as a `RigidFit` of NumPy arrays (``.rigid_fit()``, all fields)."""
    return _Collect(n, size, fields, advance)


@functools.partial(jax.jit, static_argnames=("window", "variants"))
def variance_chunk(x: jax.Array, window: int, variants: tuple[str, ...]) -> jax.Array:
    """`led_variances` of the frames of a chunk with a halo of half a window."""
    h = window // 2
    return jnp.stack(led_variances(x, window, variants=variants))[:, h : x.shape[0] - h]


def led_emission_angles(position, quaternion_wxyz, constellation, normals):
    """Emission angle [rad] `(frames, leds)` of each LED toward the camera at the origin of
    the camera frame, from tool poses and the constellation/normals in the tool frame."""
    return np.asarray(
        _emission_angles(
            np.asarray(position),
            np.nan_to_num(quaternion_wxyz),
            np.asarray(constellation, np.float64),
            np.asarray(normals, np.float64),
        )
    )


@jax.jit
def _emission_angles(position, quaternion_wxyz, constellation, normals):
    # component by component, `(frames, leds)` each: XLA fuses it into one loop, where
    # reductions over axes of length 3 are slow on CPU
    r = jax.vmap(lambda q: jaxlie.SO3(q).as_matrix())(quaternion_wxyz)

    def rotate(v):
        return [sum(r[:, i, c, None] * v[None, :, c] for c in range(3)) for i in range(3)]

    p = rotate(constellation)
    # the LED's direction to the camera (unnormalised: atan2 of the cross and dot
    # products needs no unit length) and its normal
    x, y, z = (-(p[i] + position[:, i, None]) for i in range(3))
    u, v, w = rotate(normals)
    cross = jnp.sqrt((y * w - z * v) ** 2 + (z * u - x * w) ** 2 + (x * v - y * u) ** 2)
    return jnp.arctan2(cross, x * u + y * v + z * w)


def _residual(model, x, quaternion_wxyz, position):
    """Distance [m] of each LED `x` `(frames, leds, 3)` from the constellation `model` at
    the given poses (NaN poses as the zero rotation at the origin, as before)."""
    r = rotation_rows(*jnp.moveaxis(jnp.nan_to_num(quaternion_wxyz), -1, 0))
    t = jnp.nan_to_num(position)
    d = [
        x[..., i] - (sum(r[i][j][:, None] * model[None, :, j] for j in range(3)) + t[:, i, None])
        for i in range(3)
    ]
    return jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])


def _noise_variance(x, seen, model, normals, noise, has_angle):
    """The ``noise_variance`` feature of a chunk: the noise model's per-axis variance at
    each observation's emission angle (from the noise fit's poses) and distance."""
    q, t, valid, angle_knots, distance_knots, table, level, fill = noise
    if has_angle and angle_knots.shape[0] > 1:
        th = jnp.where(
            seen & valid[:, None],
            _emission_angles(t, jnp.nan_to_num(q), model, normals),
            jnp.nan,
        )
        th = jnp.where(jnp.isfinite(th), th, fill)
    else:
        th = jnp.zeros(seen.shape, x.dtype)
    return _observation_variance(x, th, angle_knots, distance_knots, table, level)


@functools.partial(
    jax.jit,
    static_argnames=("weighting", "params", "window", "variants", "needs", "noise_angle"),
)
def _pose_chunk(
    model,
    x_halo,
    usable,
    prev,
    noise,
    normals,
    scale,
    *,
    weighting,
    params,
    window,
    variants,
    needs,
    noise_angle,
):
    """Features, weights and poses of one chunk (`x_halo`: its positions with half a
    window on each side). `weighting` None: every usable LED seen counts the same."""
    h = window // 2
    x = x_halo[h : x_halo.shape[0] - h]
    seen = jnp.all(jnp.isfinite(x), axis=-1) & usable[None]
    if weighting is None:
        return weighted_procrustes(model, x, seen.astype(x.dtype))
    nan = jnp.full(seen.shape, jnp.nan, x.dtype)
    found = {}
    if variants:
        v = led_variances(x_halo, window, variants=variants)
        found = {k: a[h : x_halo.shape[0] - h] for k, a in zip(variants, v)}
    residual, angle = jnp.zeros(seen.shape, x.dtype), nan
    if prev is not None:
        q, t, valid = prev
        if "residual" in needs:
            residual = jnp.nan_to_num(_residual(model, x, q, t))
        if "emission_angle" in needs:
            th = _emission_angles(t, jnp.nan_to_num(q), model, normals)
            angle = jnp.where(seen & valid[:, None], th, jnp.nan)
    features = LedFeatures(
        visible=seen,
        variance=found.get("paper", nan),
        pairwise_variance=found.get("pairwise", nan),
        residual=residual,
        emission_angle=angle,
        noise_variance=(
            nan if noise is None else _noise_variance(x, seen, model, normals, noise, noise_angle)
        ),
        residual_scale=scale,
    )
    weights = get_weighting(weighting)(features, **dict(params))
    return weighted_procrustes(model, x, weights)


def _pose_slabs(fit: PoseArrays, a: int, size: int, halo: int = 0):
    return (
        jax.device_put(slab(fit.quaternion_wxyz, a, size, halo, np.nan)),
        jax.device_put(slab(fit.position, a, size, halo, np.nan)),
        jax.device_put(slab(fit.valid, a, size, halo, False)),
    )


def pose_pass(
    source: FrameArray,
    constellation: np.ndarray,
    usable: np.ndarray,
    *,
    weighting: str | None = None,
    params: dict | None = None,
    window: int = 1,
    variants: tuple[str, ...] = (),
    needs: frozenset[str] = frozenset(),
    prev: PoseArrays | None = None,
    noise: NoiseInputs | None = None,
    normals: np.ndarray | None = None,
    scale: float | None = None,
    chunk: int = CHUNK,
    advance: Callable = lambda n=1: None,
) -> PoseArrays:
    """Poses of every frame of `source` `(N, M, 3)` by one pass: weights of scheme
    `weighting` from the features it `needs` (uniform over the `usable` LEDs seen if
    None), `prev` the previous pass's poses (residuals, emission angles), `noise` the
    noise model's inputs, `scale` the ``residual_scale``."""
    n = source.shape[0]
    win = window if variants else 1  # no LED variance, no halo
    h = win // 2
    size = chunk_length(n, chunk)
    model = jnp.asarray(constellation)
    usable_j = jnp.asarray(usable)
    normals_j = None if normals is None else jnp.asarray(normals, jnp.float64)
    scale_j = None if scale is None else jnp.asarray(scale, jnp.float64)
    uses_prev = prev is not None and bool(needs & {"residual", "emission_angle"})
    noise_model = None
    if noise is not None:
        m = noise.model
        noise_model = (m.angle_knots, m.distance_knots, m.variance, m.led_level, noise.fill)
        noise_model = tuple(jnp.asarray(v, jnp.float64) for v in noise_model)

    def prepare(a):
        x = jax.device_put(slab(source, a, size, h, np.nan))
        p = _pose_slabs(prev, a, size) if uses_prev else None
        nz = None if noise is None else (*_pose_slabs(noise.fit, a, size), *noise_model)
        return x, p, nz

    def compute(x, p, nz):
        return _pose_chunk(
            model,
            x,
            usable_j,
            p,
            nz,
            normals_j,
            scale_j,
            weighting=weighting,
            params=tuple(sorted((params or {}).items())),
            window=win,
            variants=variants,
            needs=needs,
            noise_angle=bool(noise is not None and noise.has_angle),
        )

    collect = collect_fit(n, size, advance)
    over_chunks(n, size, prepare, compute, collect)
    return PoseArrays(**collect.out)
