"""Suite-wide settings: one thread per worker where the workers fill the cores, float64
JAX, a non-interactive matplotlib backend, and room for the kernels a worker compiles
over many test files."""

import os


def _one_thread_per_worker():
    """Workers that fill the cores run one thread each (XLA's intra-op pool and BLAS):
    two workers of two threads each on two cores spend a third of their time contending
    (two copies of the 20-seed null test: 118 s together, 82 s one thread each; 43 s
    one alone)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers < 2 or (os.cpu_count() or 1) // workers > 1:
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if "intra_op_parallelism_threads" not in flags and "multi_thread_eigen" not in flags:
        extra = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
        os.environ["XLA_FLAGS"] = f"{flags} {extra}".strip()
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    # a plugin may have loaded numpy's BLAS already (the variables above then reach only
    # the subprocesses)
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")


_one_thread_per_worker()
os.environ.setdefault("MPLBACKEND", "Agg")
# JAX's persistent compilation cache of the CLI is off in the suite: the workers would
# share one directory, serialise on its lock and write every kernel they compile.
os.environ.setdefault("ROBTRAJ_JAX_CACHE", "off")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import pytest  # noqa: E402

from robtraj._mappings import make_room  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _room_for_kernels():
    """After each test file, JAX's compiled kernels are cleared once they hold half the
    process's memory mappings: a worker runs hundreds of files, and one that reaches
    the limit dies inside XLA's compiler (`robtraj._mappings`)."""
    yield
    make_room(0.5)
