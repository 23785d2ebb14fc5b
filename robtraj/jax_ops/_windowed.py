"""Centred windowed moments of masked series with block-local prefix sums.

A kernel about the time axis (STYLE L3 exception): whole-array expressions along
`frames`, batched over a trailing series axis.

Numerics. A plain ``cumsum`` of ``x`` and ``x²`` over a whole recording turns the
windowed variance into the difference of two numbers of size ``N·x²``: for distances of
~0.1 m with µm noise that cancellation destroys every digit. Instead:

- the frames are cut into blocks of ``B = 2h + 1`` frames (``h = window // 2``), so the
  centred window of a frame covers a suffix of the previous block and a prefix of its
  own block, or a suffix of its own block and a prefix of the next one; prefix sums
  restart in each block, so every partial sum has the size of one window, whatever the
  length of the recording (counts are sums of at most B ones: exact in float32 too);
- inside a block the series is shifted by the block's mean of valid values; each of the
  two partial windows is reduced to (count, mean, m2) about its own mean, and the two are
  combined with Chan's parallel-variance update, so no sum is taken about a distant value.

The relative error of a variance is about ``eps · (spread within the block / spread
within the window)²``: ~1e-15 for a smooth series in float64, more only in windows
next to (not over) a jump of the series. Work is O(frames · series): a prefix sum over
the block axis plus elementwise updates, independent of the window length.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float


def windowed_moments(
    x: Float[Array, "frames series"],
    valid: Bool[Array, "frames series"],
    half_width: int,
) -> tuple[
    Float[Array, "frames series"], Float[Array, "frames series"], Float[Array, "frames series"]
]:
    """Count, mean and sum of squared deviations of `x` over frames ``s-h .. s+h``.

    Frames outside ``[0, N)`` and frames with ``valid`` false do not count; `x` may hold
    NaN there (it reaches neither values nor gradients). Returns ``(count, mean, m2)``
    with the dtype of `x`; ``mean`` and ``m2`` are 0 where ``count`` is 0. The population
    variance is ``m2 / count``.
    """
    h = int(half_width)
    n, n_series = x.shape
    dtype = x.dtype
    block = 2 * h + 1
    nb = -(-n // block)
    padded = nb * block

    # Make masked values safe before any arithmetic (double-where).
    one = valid.astype(dtype)
    xs = jnp.where(valid, x, 0.0)
    if padded != n:
        one = jnp.pad(one, ((0, padded - n), (0, 0)))
        xs = jnp.pad(xs, ((0, padded - n), (0, 0)))
    # Block axis first, (B, nb, S): prefix sums and slices run over contiguous slabs.
    one = jnp.swapaxes(one.reshape(nb, block, n_series), 0, 1)
    xs = jnp.swapaxes(xs.reshape(nb, block, n_series), 0, 1)

    # Block reference: mean of the valid values in the block (0 for an empty block).
    cnt_b = jnp.sum(one, axis=0, keepdims=True)
    ref_b = jnp.sum(xs, axis=0, keepdims=True) / jnp.where(cnt_b > 0, cnt_b, 1.0)
    y = jnp.where(one > 0, xs - ref_b, 0.0)

    # In-block prefix sums of (1, y, y²) with a leading 0: pz[j] = sum of the first j
    # frames of the block, j = 0 .. B. A sequential scan over the B slabs is O(N) work
    # (jnp.cumsum's associative scan costs several passes on CPU).
    mom = jnp.stack([one, y, y * y], axis=1)  # (B, 3, nb, S)

    def step(carry, v):
        carry = carry + v
        return carry, carry

    _, pz = jax.lax.scan(step, jnp.zeros_like(mom[0]), mom)
    pz = jnp.concatenate([jnp.zeros_like(mom[:1]), pz], axis=0)  # (B + 1, 3, nb, S)
    total = pz[block:]  # (1, 3, nb, S)

    # Frame i (0..B-1) of block b: own block covers positions max(i-h, 0) .. min(i+h, B-1).
    hi = jnp.concatenate([pz[h + 1 :], jnp.broadcast_to(total, pz[:h].shape)], axis=0)
    lo = jnp.concatenate([jnp.zeros_like(pz[: h + 1]), pz[1 : h + 1]], axis=0)
    own = hi - lo
    # Previous block, for i < h: its suffix from position i + h + 1.
    prev_suffix = total - pz[h + 1 : block]  # (h, 3, nb, S)
    prev_suffix = jnp.pad(prev_suffix, ((0, 0), (0, 0), (1, 0), (0, 0)))[:, :, :-1]
    # Next block, for i > h: its prefix of i - h frames.
    next_prefix = jnp.pad(pz[1 : h + 1], ((0, 0), (0, 0), (0, 1), (0, 0)))[:, :, 1:]
    other = jnp.concatenate([prev_suffix, jnp.zeros_like(total), next_prefix], axis=0)
    ref_prev = jnp.pad(ref_b, ((0, 0), (1, 0), (0, 0)))[:, :-1]
    ref_next = jnp.pad(ref_b, ((0, 0), (0, 1), (0, 0)))[:, 1:]
    ref_other = jnp.concatenate(
        [
            jnp.broadcast_to(ref_prev, (h, nb, n_series)),
            ref_b,
            jnp.broadcast_to(ref_next, (h, nb, n_series)),
        ],
        axis=0,
    )

    def reduce(k, s1, s2, ref):
        safe = jnp.where(k > 0, k, 1.0)
        dev = jnp.where(k > 0, s1 / safe, 0.0)
        return dev + ref, jnp.maximum(s2 - s1 * dev, 0.0)

    k_own, k_oth = own[:, 0], other[:, 0]
    mean_own, m2_own = reduce(k_own, own[:, 1], own[:, 2], ref_b)
    mean_oth, m2_oth = reduce(k_oth, other[:, 1], other[:, 2], ref_other)
    # Chan et al.: combine two partial windows about their own means.
    count = k_own + k_oth
    safe = jnp.where(count > 0, count, 1.0)
    frac_oth = k_oth / safe
    delta = jnp.where((k_own > 0) & (k_oth > 0), mean_oth - mean_own, 0.0)
    mean = jnp.where(count > 0, mean_own + frac_oth * delta, 0.0)
    m2 = m2_own + m2_oth + delta * delta * k_own * frac_oth

    def flat(a):
        return jnp.swapaxes(a, 0, 1).reshape(padded, n_series)[:n]

    return flat(count), flat(mean), flat(m2)


def windowed_range_is_zero(
    x: Float[Array, "frames series"],
    valid: Bool[Array, "frames series"],
    half_width: int,
) -> Bool[Array, "frames series"]:
    """True where all valid `x` in frames ``s-h .. s+h`` are equal (exact comparison).

    Windowed max and min by block prefix/suffix scans (van Herk / Gil-Werman with the same
    blocks of ``2h + 1`` frames as `windowed_moments`): O(frames · series).
    """
    h = int(half_width)
    n, n_series = x.shape
    block = 2 * h + 1
    nb = -(-n // block)
    padded = nb * block
    inf = jnp.array(jnp.inf, x.dtype)
    # stack max(x) and max(-x) = -min(x); invalid frames are -inf (neutral)
    v = jnp.stack([jnp.where(valid, x, -inf), jnp.where(valid, -x, -inf)], axis=-1)
    if padded != n:
        v = jnp.pad(v, ((0, padded - n), (0, 0), (0, 0)), constant_values=-jnp.inf)
    v = jnp.swapaxes(v.reshape(nb, block, n_series, 2), 0, 1)  # (B, nb, S, 2)

    def step(carry, u):
        carry = jnp.maximum(carry, u)
        return carry, carry

    start = jnp.full_like(v[0], -inf)
    _, pre = jax.lax.scan(step, start, v)  # pre[j] = max of positions 0..j
    _, suf = jax.lax.scan(step, start, v, reverse=True)  # suf[j] = max of j..B-1
    whole = pre[block - 1 :]  # (1, nb, S, 2)
    neg = jnp.full_like(whole, -inf)
    # own block: i < h: prefix to i + h; i == h: whole; i > h: suffix from i - h
    own = jnp.concatenate([pre[h : block - 1], whole, suf[1 : h + 1]], axis=0)
    # previous block's suffix from i + h + 1 (i < h); next block's prefix to i - h - 1
    prev = jnp.pad(suf[h + 1 :], ((0, 0), (1, 0), (0, 0), (0, 0)), constant_values=-jnp.inf)
    nxt = jnp.pad(pre[:h], ((0, 0), (0, 1), (0, 0), (0, 0)), constant_values=-jnp.inf)
    other = jnp.concatenate([prev[:, :-1], neg, nxt[:, 1:]], axis=0)
    m = jnp.maximum(own, other)
    same = m[..., 0] == -m[..., 1]
    return jnp.swapaxes(same, 0, 1).reshape(padded, n_series)[:n]
