"""XLA compiler settings, applied when robtraj is imported (before JAX starts its CPU
backend, which reads ``XLA_FLAGS`` once).

robtraj's kernels are compiled once per recording shape and run over whole recordings;
on a 2-core machine the first run of a command spends more time in XLA's CPU compiler
than in its computation. XLA's newer CPU fusion emitters (MLIR) take about twice as long
to compile the same kernels as its loop emitters, which run them within about 10 %
(measured on the calibration's normal equations, the Procrustes and LED-variance
kernels; `docs/design-notes.md`). So the loop emitters are asked for,
``--xla_cpu_use_fusion_emitters=false``, unless ``XLA_FLAGS`` already sets that flag or
``ROBTRAJ_XLA_FLAGS=off``.

XLA aborts the process on a flag it does not know, and the flag exists only in some
jaxlib releases (0.6 on; a later one may drop it): it is set only where the installed
jaxlib's libraries register it (its name as a C string in one of them).
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path

ENV = "ROBTRAJ_XLA_FLAGS"
FLAG = "xla_cpu_use_fusion_emitters"
VALUE = "false"


def jaxlib_knows(flag: str) -> bool:
    """Whether the installed jaxlib registers the XLA flag `flag` (its name appears as a
    NUL-terminated string in one of jaxlib's shared libraries)."""
    try:
        import jaxlib
    except ImportError:
        return False
    needle = b"\0" + flag.encode() + b"\0"
    for path in Path(jaxlib.__file__).parent.rglob("*.so"):
        try:
            with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as m:
                if m.find(needle) >= 0:
                    return True
        except (OSError, ValueError):  # unreadable or empty file
            continue
    return False


def set_compile_flags() -> bool:
    """Add ``--xla_cpu_use_fusion_emitters=false`` to ``XLA_FLAGS`` (module docstring);
    returns whether it is set now. No effect once JAX's backend has started."""
    flags = os.environ.get("XLA_FLAGS", "")
    if FLAG in flags:
        return f"--{FLAG}={VALUE}" in flags.split()
    if os.environ.get(ENV, "").strip().lower() in {"0", "off", "false", "no"}:
        return False
    if not jaxlib_knows(FLAG):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} --{FLAG}={VALUE}".strip()
    return True
