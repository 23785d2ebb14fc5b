"""Suite-wide settings: float64 JAX and a non-interactive matplotlib backend."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
# JAX's persistent compilation cache of the CLI is off in the suite: the workers would
# share one directory, serialise on its lock and write every kernel they compile.
os.environ.setdefault("ROBTRAJ_JAX_CACHE", "off")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
