"""A fit's work that need not wait for the rest: its kernels compiled, and the noise model
estimated, on background threads while the main thread prepares the problem.

A calibration's large kernels (the normal equations, their clustered variant, the
residual pass) depend only on the shapes of the problem, known once the observations
are chunked, not on the noise weights or the closed-form start; the noise model depends
on the recording alone; the closed-form start on neither. XLA compiles, and NumPy and
XLA compute, with the GIL released, so on a machine with a core to spare they overlap.
``jit(f).lower(args).compile()`` fills the cache that ``f(args)`` then hits.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

_COMPILE = ThreadPoolExecutor(max_workers=1, thread_name_prefix="robtraj-compile")
_WORK = ThreadPoolExecutor(max_workers=1, thread_name_prefix="robtraj-work")


def in_background(fn: Callable[..., Any], *args: Any) -> Future:
    """Run `fn(*args)` on a background thread (one at a time, in order of submission);
    its result or exception comes with ``.result()``."""
    return _WORK.submit(fn, *args)


class CompileAhead:
    """Kernels submitted for compilation (`submit`), in order, on one background thread.
    `wait` for a kernel before its first call (one called while it is still being
    compiled would be compiled twice). A kernel that fails to compile here is compiled
    again, and its error raised, by the call itself."""

    def __init__(self) -> None:
        self._futures: list[Future] = []

    def submit(self, kernel: Any, *args: Any) -> Future:
        """Compile `kernel` (a `jax.jit` or `eqx.filter_jit` function) for `args`."""
        return self.run(_compile, kernel.lower, args)

    def run(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Run `fn(*args)` on the compiling thread, after what was submitted before."""
        future = _COMPILE.submit(fn, *args)
        self._futures.append(future)
        return future

    def wait(self, *futures: Future) -> None:
        """Until `futures` (default: everything submitted) are done."""
        for future in futures or self._futures:
            future.exception()


def _compile(lower: Callable[..., Any], args: tuple) -> None:
    lower(*args).compile()
