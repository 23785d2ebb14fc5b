"""A kernel over chunks of frames with a halo, each chunk computed in cache.

A kernel about the time axis (STYLE L3 exception): the frames are cut into chunks of a
fixed length, each extended by a halo of frames on both sides (NaN beyond the ends of
the recording), and a per-chunk function maps the extended chunk to its own frames.

On CPU, two conditionals per chunk. Inside the loop over chunks (`lax.map`, a while
loop) XLA fuses the loop's dynamic slicing of the input and dynamic update of the
output into the neighbouring elementwise kernels, and on CPU it leaves such fused loops
scalar (no SIMD): for the LED-variance kernels that cost about half their time. The
results of a `lax.cond` are materialized buffers, so (1) the extended chunk is cut in a
conditional, whose two branches also handle the ends of the recording (no padded copy
of the whole input), and (2) the per-chunk function runs in a conditional whose
predicate is true at run time but not known to the compiler: its kernels read and write
plain buffers and are vectorized. Elsewhere (GPU) the input is padded once and sliced.
"""

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def map_chunks(
    fn: Callable | tuple[Callable, ...],
    x: Float[Array, "frames ..."],
    chunk: int,
    halo: int,
    *,
    frames_last: bool = False,
) -> Array:
    """``fn`` over chunks of `chunk` frames of `x`, each with `halo` frames on both sides.

    `fn` maps an extended chunk, ``chunk + 2·halo`` frames of `x` (NaN before the first
    and after the last frame), to ``(chunk, ...)`` values for the chunk's own frames.
    A tuple of functions is applied in turn, each stage's result materialized (on CPU:
    its own conditional; XLA would otherwise fuse a cheap stage's gathers into the
    next stage's transposes and leave them scalar).
    With `frames_last` it gets the extended chunk with all axes reversed, frames last
    (``(3, leds, frames)`` for ``(frames, leds, 3)`` positions). Returns
    ``(frames, ...)``: the chunks' values concatenated and cut to the length of `x`.
    """
    stages = fn if isinstance(fn, tuple) else (fn,)
    n = x.shape[0]
    size = chunk + 2 * halo
    n_chunks = -(-n // chunk)

    def cut(v):
        return jnp.transpose(v) if frames_last else v

    def on_cpu(x):
        def extended(i):
            start = i * chunk - halo

            def inside():
                return cut(jax.lax.dynamic_slice_in_dim(x, start, size, axis=0))

            def at_an_end():
                t = start + jnp.arange(size)
                seen = ((t >= 0) & (t < n)).reshape(-1, *([1] * (x.ndim - 1)))
                return cut(jnp.where(seen, x[jnp.clip(t, 0, n - 1)], jnp.nan))

            if size > n:  # no chunk lies inside
                return at_an_end()
            return jax.lax.cond((start >= 0) & (start + size <= n), inside, at_an_end)

        def step(i):
            v = extended(i)
            for stage in stages:
                out = jax.eval_shape(stage, v)
                zeros = functools.partial(jax.tree.map, lambda o: jnp.zeros(o.shape, o.dtype), out)
                v = jax.lax.cond(i >= 0, stage, lambda _: zeros(), v)
            return v

        return jax.lax.map(step, jnp.arange(n_chunks))

    def elsewhere(x):
        pad = [(halo, n_chunks * chunk - n + halo)] + [(0, 0)] * (x.ndim - 1)
        xp = jnp.pad(x, pad, constant_values=jnp.nan)

        def step(i):
            v = cut(jax.lax.dynamic_slice_in_dim(xp, i * chunk, size, axis=0))
            for stage in stages:
                v = stage(v)
            return v

        return jax.lax.map(step, jnp.arange(n_chunks))

    out = jax.lax.platform_dependent(x, cpu=on_cpu, default=elsewhere)
    return out.reshape(n_chunks * chunk, *out.shape[2:])[:n]
