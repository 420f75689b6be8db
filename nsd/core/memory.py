"""Process memory: give freed heap back to the operating system during long streaming runs,
and measure the peak resident size of one part of a run (a pipeline stage)."""

from __future__ import annotations

import ctypes
import functools
import resource
from pathlib import Path

__all__ = ["peak_rss_mb", "reset_peak_rss", "trim_heap"]


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


def reset_peak_rss() -> bool:
    """Start a new peak resident size (Linux: ``5`` to ``/proc/self/clear_refs`` resets
    VmHWM to the current size). False where it cannot (then :func:`peak_rss_mb` is the
    process's peak so far)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """The process's peak resident size in MiB since :func:`reset_peak_rss` (Linux: VmHWM,
    this process's own address space), or since it started (``ru_maxrss``, which survives
    ``exec``: a subprocess would report its parent's peak at the fork) where /proc is not
    there."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
