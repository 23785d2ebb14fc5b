"""LED quality: windowed variance of distances to the other LEDs (paper eq. 3-5)."""

import functools
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._windowed import windowed_moments, windowed_range_is_zero

# Frames per chunk of the kernel (plus a halo of half a window on each side): the
# (frames, leds, leds) pair distances of one chunk stay a few MB, in cache.
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
    is split into a piecewise-constant part (the sum of per-pair reference distances over the
    partners seen) and a small remainder; where the partner set does not change within
    the window the variance is that of the remainder, so the jumps of ``d_t`` elsewhere
    cost no precision. In float32 the positions themselves carry ~0.1 µm rounding at
    1.5 m, so the variance of ~20 µm noise is good to about 1e-2 relative.
    """
    if positions.ndim != 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be (frames, leds, 3), got {positions.shape}")
    if int(window) < 1:
        raise ValueError(f"window must be >= 1 frame, got {window}")
    if variant not in ("paper", "pairwise"):
        raise ValueError(f"variant must be 'paper' or 'pairwise', got {variant!r}")
    if not jnp.issubdtype(positions.dtype, jnp.floating):
        raise ValueError(f"positions must be floating point, got {positions.dtype}")
    if min_count is None:
        min_count = max(2, int(window) // 2)
    if positions.shape[1] < 2:
        return jnp.full(positions.shape[:2], jnp.nan, positions.dtype)
    return _led_variance(positions, int(window) // 2, variant, int(min_count))


def _chunks(x: Array, half_width: int, chunk: int) -> Array:
    """(frames, ...) -> (chunks, halo + chunk + halo, ...), NaN-padded beyond the ends."""
    n = x.shape[0]
    nc = -(-n // chunk)
    tail = [(0, 0)] * (x.ndim - 1)
    main = jnp.pad(x, [(0, nc * chunk - n)] + tail, constant_values=jnp.nan)
    main = main.reshape(nc, chunk, *x.shape[1:])
    h = half_width
    if h == 0:
        return main
    pad = jnp.full((1, h, *x.shape[1:]), jnp.nan, x.dtype)
    left = jnp.concatenate([pad, main[:-1, chunk - h :]], axis=0)
    right = jnp.concatenate([main[1:, :h], pad], axis=0)
    return jnp.concatenate([left, main, right], axis=1)


def _pair_distances(x: Array, seen: Array) -> tuple[Array, Array]:
    """Distances (frames, pairs) and where both LEDs are seen, for the LED pairs
    (a, a + k) ordered by offset k = 1 .. leds-1, then by a.

    Built from shifted slices (LED a against LED a + k), not gathers: XLA's gather is
    slow on CPU.
    """
    m = seen.shape[1]

    def pairs(v, op):
        return jnp.concatenate([op(v[:, : m - k], v[:, k:]) for k in range(1, m)], axis=1)

    both = pairs(seen, jnp.logical_and)
    diff = [pairs(x[..., i], jnp.subtract) for i in range(3)]
    # explicit order: the same rounding whatever the fusion or sharding
    sq = (diff[0] * diff[0] + diff[1] * diff[1]) + diff[2] * diff[2]
    # double-where: sqrt has an infinite derivative at 0 (unseen partners).
    return jnp.where(both, jnp.sqrt(jnp.where(both, sq, 1.0)), 0.0), both


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _led_variance(positions: Array, half_width: int, variant: str, min_count: int) -> Array:
    dtype = positions.dtype
    n, n_leds, _ = positions.shape
    h = half_width
    chunk = max(_CHUNK, h)

    # pairs (a, a + k) in the order of `_pair_distances`; incidence (pairs, leds)
    pair_a = np.concatenate([np.arange(n_leds - k) for k in range(1, n_leds)])
    pair_b = np.concatenate([np.arange(k, n_leds) for k in range(1, n_leds)])
    leds = np.arange(n_leds)
    incidence = jnp.asarray((pair_a[:, None] == leds) | (pair_b[:, None] == leds), dtype)

    def to_leds(v):
        """(..., pairs) -> (..., leds): for each LED the sum over the pairs it is in, as
        one matmul (exact: at most leds - 1 non-zero terms; HIGHEST keeps float32 out of
        reduced-precision GPU matmuls). XLA's scatter is slow on CPU."""
        return jnp.matmul(v, incidence, precision=jax.lax.Precision.HIGHEST)

    def prepare(x):
        seen = jnp.all(jnp.isfinite(x), axis=-1)
        return jnp.where(seen[..., None], x, 0.0), seen

    if variant == "paper":

        def paper_chunk(xc):
            x, seen = prepare(xc)
            # All (a, b) pairs as (frames, leds, leds) broadcasts reduced over b: one
            # fused loop, no gathers (twice the distances of a < b, still cheaper).
            both = seen[:, :, None] & seen[:, None, :] & ~np.eye(n_leds, dtype=bool)
            sq = 0.0
            for i in range(3):
                diff = x[:, :, None, i] - x[:, None, :, i]
                sq = sq + diff * diff
            # double-where: sqrt has an infinite derivative at 0 (unseen partners).
            dist = jnp.where(both, jnp.sqrt(jnp.where(both, sq, 1.0)), 0.0)
            # Per-pair reference distance ref_ab: d = e + r with r = Σ_b ref_ab piecewise
            # constant (it changes only when partners come and go) and e small. ref_ab is
            # the distance at the first frame of the chunk (halo included) where both are
            # seen: every window lies inside one chunk, and the chunks do not depend on
            # how the frames are split across devices.
            first = jnp.argmax(both, axis=0)
            ref = jax.lax.stop_gradient(jnp.take_along_axis(dist, first[None], axis=0))
            # paper eq. 4: d = sum over the partners seen at t; also e, r, partner count
            d = jnp.sum(dist, axis=2)
            e = jnp.sum(jnp.where(both, dist - ref, 0.0), axis=2)
            r = jnp.sum(jnp.where(both, ref, 0.0), axis=2)
            k = jnp.sum(both, axis=2)
            ok = seen & (k > 0)
            count, _, m2 = windowed_moments(
                jnp.concatenate([d, e], axis=1), jnp.tile(ok, (1, 2)), h
            )
            count, m2_d, m2_e = count[:, :n_leds], m2[:, :n_leds], m2[:, n_leds:]
            # Where the partner set (hence r) is constant over the window, var(d) =
            # var(e) exactly and var(e) has no cancellation; elsewhere the jump
            # dominates var(d).
            constant = windowed_range_is_zero(r, ok, h)
            m2 = jnp.where(constant, m2_e, m2_d)
            # paper eq. 3 and 5: population variance over the valid window frames
            var = m2 / jnp.where(count > 0, count, 1.0)
            out = jnp.where(seen & (count >= min_count), var, jnp.nan)
            return out[h : h + chunk]

        body = paper_chunk
    else:

        def body(xc):
            x, seen = prepare(xc)
            dist, both = _pair_distances(x, seen)
            count, _, m2 = windowed_moments(dist, both, h)
            use = count >= min_count
            var = jnp.where(use, m2 / jnp.where(use, count, 1.0), 0.0)
            total, n_use = to_leds(jnp.stack([var, use.astype(dtype)]))
            mean = total / jnp.where(n_use > 0, n_use, 1.0)
            return jnp.where(seen & (n_use > 0), mean, jnp.nan)[h : h + chunk]

    out = jax.lax.map(body, _chunks(positions, h, chunk))
    return out.reshape(-1, n_leds)[:n].astype(dtype)
