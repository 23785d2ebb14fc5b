"""Recording-level statistics for the pose passes, each in passes of its own over the
frames and a previous pass's poses: the noise model of the recording
(`noise_inputs`: `estimate_noise` from the frame triples it uses, and the median emission
angle) and the robust residual scale (`residual_scale`), both exact, in small memory."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..recording import FrameArray, finite_points
from ._chunks import CHUNK, chunk_length, over_chunks, slab
from ._exact_median import ExactMedian
from ._noise import noise_from_triples, pick_triples
from ._pose_passes import NoiseInputs, PoseArrays, _emission_angles, _pose_slabs, _residual


@functools.partial(jax.jit, static_argnames=("what",))
def _fit_feature(model, normals, x, usable, q, t, valid, *, what):
    """|residual| [m] (``what="residual"``) or emission angle [rad] (``"angle"``) of the
    usable LEDs seen in a chunk at the fit's poses; NaN elsewhere."""
    seen = jnp.all(jnp.isfinite(x), axis=-1) & usable[None]
    if what == "residual":
        return jnp.where(seen, jnp.abs(jnp.nan_to_num(_residual(model, x, q, t))), jnp.nan)
    th = _emission_angles(t, jnp.nan_to_num(q), model, normals)
    return jnp.where(seen & valid[:, None], th, jnp.nan)


def _feature_pass(
    source, constellation, usable, normals, fit, what, visit, chunk, halo=0, advance=None
):
    """`visit(a, x, feature)` per chunk: `x` the chunk's positions and `feature` the fit's
    `_fit_feature`, both with `halo` frames on each side (NaN beyond the ends)."""
    n = source.shape[0]
    size = chunk_length(n, chunk)
    model = jnp.asarray(constellation)
    usable_j = jnp.asarray(usable)
    normals_j = jnp.zeros_like(model) if normals is None else jnp.asarray(normals, jnp.float64)

    def prepare(a):
        x = slab(source, a, size, halo, np.nan)
        return x, jax.device_put(x), _pose_slabs(fit, a, size, halo)

    def compute(x, xj, pose):
        return x, _fit_feature(model, normals_j, xj, usable_j, *pose, what=what)

    def collect(a, result):
        x, feature = result
        visit(a, x, np.asarray(feature))
        if advance is not None:
            advance(min(n, a + size) - a)

    over_chunks(n, size, prepare, compute, collect)


def residual_scale(
    source: FrameArray,
    constellation: np.ndarray,
    usable: np.ndarray,
    fit: PoseArrays,
    chunk: int = CHUNK,
    advance: Callable | None = None,
) -> float:
    """``residual_scale``: 1.4826 × the median |residual| at the `fit`'s poses of the
    usable LEDs seen, over the whole recording (exact: two passes)."""
    n = source.shape[0]
    size = chunk_length(n, chunk)
    median = ExactMedian()
    for step in (median.count, median.keep):
        _feature_pass(
            source,
            constellation,
            usable,
            None,
            fit,
            "residual",
            lambda a, x, r, step=step: step(r[: min(n, a + size) - a]),
            chunk,
            advance=advance,
        )
        if not median.needed():
            break
    return 1.4826 * median.value()


def noise_inputs(
    source: FrameArray,
    constellation: np.ndarray,
    usable: np.ndarray,
    normals: np.ndarray | None,
    fit: PoseArrays,
    led_ids: np.ndarray,
    chunk: int = CHUNK,
    advance: Callable | None = None,
) -> NoiseInputs:
    """The noise model of the recording (`estimate_noise` of the positions and the
    emission angles at the `fit`'s poses; without `normals`, of distance and LED only) and
    the median angle, in two passes: which frame triples see two LEDs and the angles'
    histogram, then the chosen triples and the median's bins."""
    n, m = source.shape[:2]
    size = chunk_length(n, chunk)
    angled = normals is not None
    starts = {True: np.zeros(max(n - 2, 0), bool), False: np.zeros(max(n - 2, 0), bool)}
    median = ExactMedian()
    seen_angle = [False]

    def seen_by(x, th, with_angle):
        seen = finite_points(x)
        return seen & np.isfinite(th) if with_angle else seen

    def triples(seen):
        return seen[:-2] & seen[1:-1] & seen[2:]  # rows: first frames of the triples

    def first_pass(a, x, th):
        b = min(n, a + size)
        mine = th[2 : 2 + b - a]
        median.count(mine)
        seen_angle[0] |= bool(np.isfinite(mine).any())
        # slab row i + 2 is frame a + i: the triples starting at frames a .. b - 1
        e = min(b, n - 2) - a
        if e > 0:
            for with_angle in (True, False) if angled else (False,):
                trip = triples(seen_by(x, th, with_angle))[2 : 2 + e]
                starts[with_angle][a : a + e] = trip.sum(1) >= 2

    _feature_pass(
        source, constellation, usable, normals, fit, "angle", first_pass, chunk, 2, advance
    )
    has_angle = angled and seen_angle[0]
    cand = pick_triples(starts[has_angle])
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def second_pass(a, x, th):
        b = min(n, a + size)
        if has_angle:
            median.keep(th[2 : 2 + b - a])
        mine = cand[(cand >= a) & (cand < b)]
        if mine.size:
            th = th if has_angle else np.zeros(th.shape)
            rows = (mine - a + 2)[:, None] + np.arange(3)
            seen = triples(seen_by(x, th, has_angle))[mine - a + 2]
            parts.append((x[rows], th[rows], seen))

    _feature_pass(
        source, constellation, usable, normals, fit, "angle", second_pass, chunk, 2, advance
    )
    pos, th, seen = (np.concatenate(p) for p in zip(*parts))
    model = noise_from_triples(pos, th, seen, led_ids, has_angle=has_angle)
    return NoiseInputs(model, fit, median.value() if has_angle else 0.0, has_angle)
