"""Suite-wide settings: float64 JAX and a non-interactive matplotlib backend."""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")
# JAX's persistent compilation cache of the CLI: a per-run temporary directory, never the
# user's ~/.cache.
if "ROBTRAJ_JAX_CACHE" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="robtraj-jax-cache-")
    os.environ["ROBTRAJ_JAX_CACHE"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
