"""The process heap: freed buffers of a pass over a recording go back to the system."""

from __future__ import annotations


def return_freed_memory() -> None:
    """Have glibc hand buffers of 1 MiB or more back to the system when they are freed:
    every pass over a recording allocates and frees blocks of frames, which its heap
    would otherwise keep (resident memory growing with the passes, not with the data).
    Nothing where the C library is not glibc."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").mallopt(-3, 1 << 20)  # M_MMAP_THRESHOLD
    except (OSError, AttributeError):
        pass
