"""The process's memory mappings against the kernel's limit on them.

Every kernel XLA compiles for the CPU holds 15–25 memory mappings of its own (its code
and data sections) for as long as JAX keeps it cached. A process that reaches Linux's
``vm.max_map_count`` (65530 by default, about 2 800 kernels) dies with SIGSEGV inside
XLA's compiler the next time it compiles: a long notebook session or test run, never
one command. `make_room` clears JAX's caches, and the kernels with them, before that.
"""

from __future__ import annotations

from pathlib import Path

MAPS = Path("/proc/self/maps")
LIMIT = Path("/proc/sys/vm/max_map_count")


def mapping_count() -> int | None:
    """Memory mappings the process holds now (None where the system does not say)."""
    try:
        return MAPS.read_bytes().count(b"\n")
    except OSError:
        return None


def mapping_limit() -> int | None:
    """The most memory mappings a process may hold (None where the system does not say)."""
    try:
        return int(LIMIT.read_text())
    except (OSError, ValueError):
        return None


def make_room(fraction: float = 0.8, limit: int | None = None) -> str | None:
    """Clear JAX's caches (its compiled kernels, which later calls compile again) when
    the process holds more than `fraction` of `limit` memory mappings (default: the
    system's); returns what it did in words, None when there was room."""
    limit = mapping_limit() if limit is None else limit
    held = mapping_count()
    if limit is None or held is None or held <= fraction * limit:
        return None
    import jax

    jax.clear_caches()
    return (
        f"JAX's compiled kernels cleared: the process held {held} of at most {limit} "
        f"memory mappings (vm.max_map_count), now {mapping_count()}; they compile again "
        "when next called"
    )
