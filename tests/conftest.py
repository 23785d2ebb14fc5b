"""Suite-wide settings: float64 JAX, a non-interactive matplotlib backend, and room for
the kernels a worker compiles over many test files."""

import os

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
