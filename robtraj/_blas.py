"""One BLAS thread for NumPy/SciPy linear algebra between JAX kernels.

JAX's CPU runtime keeps its own thread pool, whose workers spin for a while after each
kernel; OpenBLAS's threads (NumPy's and SciPy's, and LAPACK's inside jaxlib) then contend
with them for the cores. On the 2-core reference machine a 100×1100 by 1100×100 product
took 13× longer after a JAX kernel than before it, and the pose-level workflow
(`robtraj.analysis.real_data.run_workflow`: thousands of dense solves of 100–1600
parameters, each followed by a JAX pass over the poses) ran 20 % faster with one BLAS
thread. `serial_blas` limits the BLAS libraries to one thread while the function runs
(`threadpoolctl`; the user's setting is restored afterwards).

OpenBLAS's limit is process-wide, and threadpoolctl lets only the thread that set it
change it back while that thread lives: the outermost decorated call should run on a
thread that outlives the ones it starts (as `run_workflow` does). Two unrelated threads
entering decorated calls at once can leave BLAS at one thread afterwards.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import TypeVar

from threadpoolctl import threadpool_limits

F = TypeVar("F", bound=Callable)

_lock = threading.Lock()
_depth = 0
_limits = None


def _enter() -> None:
    global _depth, _limits
    with _lock:
        if _depth == 0:
            _limits = threadpool_limits(1, user_api="blas")
        _depth += 1


def _exit() -> None:
    global _depth, _limits
    with _lock:
        _depth -= 1
        if _depth == 0:
            _limits.restore_original_limits()
            _limits = None


def serial_blas(fn: F) -> F:
    """`fn` run with one BLAS thread (module docstring). Nested and concurrent calls
    (threads) share one limit, set by the first to enter and lifted by the last to
    leave."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        _enter()
        try:
            return fn(*args, **kwargs)
        finally:
            _exit()

    return wrapper  # type: ignore[return-value]
