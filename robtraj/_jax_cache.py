"""JAX's persistent compilation cache in the user's cache directory.

Compiled kernels are written to ``$ROBTRAJ_JAX_CACHE`` if set, else to the platform's
user cache directory (``$XDG_CACHE_HOME/robtraj/jax`` or ``~/.cache/robtraj/jax`` on
Linux, ``~/Library/Caches/robtraj/jax`` on macOS, ``%LOCALAPPDATA%\\robtraj\\jax`` on
Windows), so a second run of a command skips the JIT compilation.
``ROBTRAJ_JAX_CACHE=off`` (or ``0``) disables it.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ENV = "ROBTRAJ_JAX_CACHE"
_OFF = {"0", "off", "false", "no", "none"}


def compilation_cache_dir() -> Path | None:
    """Where compiled kernels are cached, or None when disabled."""
    value = os.environ.get(ENV, "").strip()
    if value.lower() in _OFF:
        return None
    if value:
        return Path(value).expanduser()
    if sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    elif sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "robtraj" / "jax"


def enable_compilation_cache() -> Path | None:
    """Turn on JAX's persistent compilation cache; returns its directory (None: off or
    not writable, then everything still works, only without the cache)."""
    import jax

    path = compilation_cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(path, os.W_OK):
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # cache every kernel, however quick to compile: a calibration compiles some seventy
    # small ones (tens of ms each, about 2 s in all) besides its large ones
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
