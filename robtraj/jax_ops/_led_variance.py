"""LED quality: windowed variance of distances to the other LEDs (paper eq. 3-5)."""

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._chunked import map_chunks
from ._windowed import windowed_moments, windowed_range_is_zero

# Frames per chunk of the kernel (plus a halo of half a window on each side): the
# (pairs, frames) distances of one chunk stay a few MB, in cache.
_CHUNK = 2048


def led_variance(
    positions: Float[Array, "frames leds 3"],
    window: int,
    *,
    variant: Literal["paper", "pairwise"] = "paper",
    min_count: int | None = None,
) -> Float[Array, "frames leds"]:
    """Per-frame, per-LED variance of inter-LED distances over a centred window.

    **Arguments:**

    - `positions`: `(frames, leds, 3)` LED positions in the camera frame [m], NaN where an
      LED is not seen. Any float dtype; the result has the same dtype.
    - `window`: window length n [frames]. The window of frame s holds frames
      ``s - h .. s + h`` with ``h = window // 2`` (``2h + 1`` frames; clipped at the ends
      of the recording), as in paper eq. 3 (``t = s - n/2 .. s + n/2``).
    - `variant`:
        - ``"paper"`` (paper eq. 3-5): ``d_t`` = sum of the distances from LED a to the
          other LEDs seen at frame t (eq. 4); ``v_s`` = population variance of ``d_t``
          over the window (``1/count``, ddof=0: the paper's ``1/n`` in eq. 3 and 5, with
          n the number of frames that count). Frames where a is unseen, or where no other
          LED is seen, do not count. ``d_t`` jumps when partners appear or disappear,
          which shows up as variance (as in the paper's figure 3).
        - ``"pairwise"``: for every partner b, the population variance of the distance
          |a - b| over the window frames where both are seen; ``v_s`` = mean over the
          partners with at least `min_count` common frames in the window. Does not jump
          when partners appear or disappear.
    - `min_count`: fewest valid frames in the window for a value; default
      ``max(2, window // 2)``.

    **Returns:**

    `(frames, leds)` variance [m²]; NaN where the LED is not seen at that frame or fewer
    than `min_count` valid frames are in its window (for ``"pairwise"``: no partner has).

    Cost O(frames · leds²) time, independent of the window length (block-local prefix
    sums, see `windowed_moments`), and O(frames · leds) memory: the frames are processed
    in chunks of a few thousand (each with a halo of half a window), so the
    (frames, pairs) distances exist for one chunk at a time. Frame-sharded inputs work
    (XLA inserts the collectives) and give bitwise the same result.

    Precision: float64 agrees with a direct two-pass evaluation to ~1e-12 relative on
    0.1 m constellations with 15 µm noise (the rounding of the distances themselves,
    1 ulp of 0.1 m against ~20 µm noise, sets that floor). For the paper variant ``d_t``
    is split into a piecewise-constant part (the sum of per-pair reference distances
    over the partners seen, exact) and a small remainder; where the partner set does not
    change within the window the variance is that of the remainder, so the jumps of
    ``d_t`` elsewhere cost no precision. In float32 the positions themselves carry ~0.1 µm rounding at
    1.5 m, so the variance of ~20 µm noise is good to about 1e-2 relative.
    """
    if variant not in ("paper", "pairwise"):
        raise ValueError(f"variant must be 'paper' or 'pairwise', got {variant!r}")
    (variance,) = led_variances(positions, window, variants=(variant,), min_count=min_count)
    return variance


def led_variances(
    positions: Float[Array, "frames leds 3"],
    window: int,
    *,
    variants: tuple[str, ...] = ("paper", "pairwise"),
    min_count: int | None = None,
) -> tuple[Float[Array, "frames leds"], ...]:
    """`led_variance` of several variants in one pass, in the order of `variants`.

    The pair distances and the windowed sums are computed once for all of them: both
    variants together cost little more than the pairwise one alone.
    """
    if positions.ndim != 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be (frames, leds, 3), got {positions.shape}")
    if int(window) < 1:
        raise ValueError(f"window must be >= 1 frame, got {window}")
    unknown = [v for v in variants if v not in ("paper", "pairwise")]
    if unknown or not variants:
        raise ValueError(f"variants must be 'paper' or 'pairwise', got {variants!r}")
    if not jnp.issubdtype(positions.dtype, jnp.floating):
        raise ValueError(f"positions must be floating point, got {positions.dtype}")
    if min_count is None:
        min_count = max(2, int(window) // 2)
    if positions.shape[1] < 2:
        return tuple(jnp.full(positions.shape[:2], jnp.nan, positions.dtype) for _ in variants)
    out = _led_variances(positions, int(window) // 2, tuple(variants), int(min_count))
    return tuple(out[:, k] for k in range(len(variants)))


def _pair_index(n_leds: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LED pairs (a, a + k) ordered by offset k = 1 .. leds-1, then by a, as indices
    ``pair_a``, ``pair_b``; and for each LED the pairs it is in, by partner:
    ``(leds, leds - 1)``."""
    pair_a = np.concatenate([np.arange(n_leds - k) for k in range(1, n_leds)])
    pair_b = np.concatenate([np.arange(k, n_leds) for k in range(1, n_leds)])
    partner = np.zeros((n_leds, n_leds - 1), np.int32)
    for a in range(n_leds):
        partner[a] = np.flatnonzero((pair_a == a) | (pair_b == a))
    return pair_a, pair_b, partner


def _distance_sums(xt: Float[Array, "3 leds frames"], variants: tuple[str, ...]) -> dict:
    """Pair distances and, for the paper variant, eq. 4, for one extended chunk with the
    frames last: ``(3, leds, frames)`` positions in, ``(…, frames)`` arrays out.

    - ``seen`` `(leds, frames)`.
    - pairwise: ``dist`` and ``both`` `(pairs, frames)`, the distance of each pair of
      `_pair_index` and where both LEDs are seen.
    - paper: ``e`` and ``r`` `(leds, frames)` with ``d = e + r`` the sum of the
      distances to the other LEDs seen, ``r`` the sum of per-pair reference distances
      over those partners (piecewise constant, exact) and ``e`` the small remainder;
      ``k`` the number of partners seen.

    Each pair's distance is computed once (pairs as rows, frames along the vector
    lanes) and added to both of its LEDs by gathering whole rows (contiguous, unlike
    the element gathers that are slow on CPU). The reference distance of a pair is its
    distance at the first frame of the chunk where both are seen, rounded to a grid
    coarse enough that any sum of at most `leds` of them is exact: ``r`` is then exactly
    constant wherever the partner set is (and computed by a matmul).
    """
    _, n_leds, _ = xt.shape
    dtype = xt.dtype
    seen = jnp.all(jnp.isfinite(xt), axis=0)
    x = jnp.where(seen, xt, 0.0)
    pair_a, pair_b, partner = _pair_index(n_leds)
    both = seen[pair_a] & seen[pair_b]
    diff = [x[i][pair_a] - x[i][pair_b] for i in range(3)]
    # explicit order: the same rounding whatever the fusion or sharding
    sq = (diff[0] * diff[0] + diff[1] * diff[1]) + diff[2] * diff[2]
    # double-where: sqrt has an infinite derivative at 0 (unseen partners).
    dist = jnp.sqrt(jnp.where(both, sq, 1.0))
    out = {"seen": seen}
    if "pairwise" in variants:
        out["dist"] = jnp.where(both, dist, 0.0)
        out["both"] = both
    if "paper" in variants:
        first = jnp.argmax(both, axis=1)
        at_first = x[:, pair_a, first] - x[:, pair_b, first]
        ref = jnp.sqrt(jnp.sum(at_first * at_first, axis=0))
        bits = jnp.finfo(dtype).nmant - int(np.ceil(np.log2(n_leds))) - 1
        _, exponent = jnp.frexp(jnp.max(ref))
        grid = jnp.ldexp(jnp.ones((), dtype), exponent - bits)
        ref = jax.lax.stop_gradient(jnp.round(ref / grid) * grid)
        dev = jnp.where(both, dist - ref[:, None], 0.0)
        e = dev[partner[:, 0]]
        for j in range(1, n_leds - 1):
            e = e + dev[partner[:, j]]
        ref_matrix = jnp.zeros((n_leds, n_leds), dtype).at[pair_a, pair_b].set(ref)
        seen_f = seen.astype(dtype)
        hp = jax.lax.Precision.HIGHEST
        out["e"] = e
        out["r"] = seen_f * jnp.matmul(ref_matrix + ref_matrix.T, seen_f, precision=hp)
        out["k"] = seen * (jnp.sum(seen, axis=0, keepdims=True) - 1)
    return out


def _chunk_variances(
    sums: dict, h: int, min_count: int, variants: tuple[str, ...]
) -> Float[Array, "frames variants leds"]:
    """The variants' variances of an extended chunk's own frames from its
    `_distance_sums`: one windowed pass over all the series they need."""
    seen = sums["seen"].T
    n_leds = seen.shape[1]
    series, valid = [], []
    if "paper" in variants:
        ok = seen & (sums["k"].T > 0)
        e = sums["e"].T
        series += [e + sums["r"].T, e]
        valid += [ok, ok]
    if "pairwise" in variants:
        series.append(sums["dist"].T)
        valid.append(sums["both"].T)
    count, _, m2 = windowed_moments(jnp.concatenate(series, axis=1), jnp.concatenate(valid, 1), h)
    out = {}
    if "paper" in variants:
        count_p, m2_d, m2_e = count[:, :n_leds], m2[:, :n_leds], m2[:, n_leds : 2 * n_leds]
        # Where the partner set (hence r) is constant over the window, var(d) = var(e)
        # exactly and var(e) has no cancellation; elsewhere the jump dominates var(d).
        constant = windowed_range_is_zero(sums["r"].T, ok, h)
        m2_p = jnp.where(constant, m2_e, m2_d)
        # paper eq. 3 and 5: population variance over the valid window frames
        var = m2_p / jnp.where(count_p > 0, count_p, 1.0)
        out["paper"] = jnp.where(seen & (count_p >= min_count), var, jnp.nan)
    if "pairwise" in variants:
        start = 2 * n_leds if "paper" in variants else 0
        count_q, m2_q = count[:, start:], m2[:, start:]
        use = count_q >= min_count
        var = jnp.where(use, m2_q / jnp.where(use, count_q, 1.0), 0.0)
        # For each LED the sum over the pairs it is in, as one matmul (exact: at most
        # leds - 1 non-zero terms; HIGHEST keeps float32 out of reduced-precision GPU
        # matmuls). XLA's scatter is slow on CPU.
        pair_a, pair_b, _ = _pair_index(n_leds)
        leds = np.arange(n_leds)
        incidence = (pair_a[:, None] == leds) | (pair_b[:, None] == leds)
        total, n_use = jnp.matmul(
            jnp.stack([var, use.astype(var.dtype)]),
            jnp.asarray(incidence, var.dtype),
            precision=jax.lax.Precision.HIGHEST,
        )
        mean = total / jnp.where(n_use > 0, n_use, 1.0)
        out["pairwise"] = jnp.where(seen & (n_use > 0), mean, jnp.nan)
    return jnp.stack([out[v] for v in variants], axis=1)[h : seen.shape[0] - h]


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _led_variances(positions: Array, half_width: int, variants: tuple, min_count: int) -> Array:
    h = half_width
    stages = (
        functools.partial(_distance_sums, variants=variants),
        functools.partial(_chunk_variances, h=h, min_count=min_count, variants=variants),
    )
    return map_chunks(stages, positions, max(_CHUNK, h), h, frames_last=True)
