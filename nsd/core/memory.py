"""Process memory: give freed heap back to the operating system during long streaming runs."""

from __future__ import annotations

import ctypes
import functools

__all__ = ["trim_heap"]


@functools.cache
def _malloc_trim():
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


def trim_heap() -> None:
    """Give freed heap memory back to the OS (glibc ``malloc_trim``; a no-op elsewhere).

    Called after every batch: without it, allocator fragmentation lets the
    resident size of a long export creep up for its first ~1,000 frames
    (``docs/benchmarks/export.md``).
    """
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
