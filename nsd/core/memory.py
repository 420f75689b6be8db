"""Process memory: keep freed heap pages for the next training step, give freed heap back to
the operating system during long streaming runs, and measure the peak resident size of one
part of a run (a pipeline stage)."""

from __future__ import annotations

import ctypes
import functools
import resource
from pathlib import Path

__all__ = ["keep_freed_heap", "peak_rss_mb", "reset_peak_rss", "trim_heap"]


# glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 * 2**20  # glibc's largest on 64-bit systems (DEFAULT_MMAP_THRESHOLD_MAX)
TRIM_THRESHOLD_KEEP = 2**31 - 1  # bytes of free heap top kept: all of it


@functools.cache
def _libc():
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.malloc_trim, libc.mallopt  # noqa: B018 (glibc has both)
        return libc
    except (OSError, AttributeError):  # not glibc
        return None


@functools.cache
def keep_freed_heap() -> bool:
    """Keep freed heap memory in the process instead of returning it to the OS at every free.

    A training step allocates and frees the same tensors of a few MB each step. glibc
    returns the freed top of the heap to the OS once it exceeds its trim threshold, and
    serves blocks above its mmap threshold from fresh mappings, so every step faulted its
    pages in again: 19,114 page faults per default step (75 MB the kernel zeroes), 77 with
    the trim threshold at its maximum and the mmap threshold at glibc's largest (32 MiB).
    A default step then runs 1.22x faster on one thread and 1.33x on two
    (``docs/benchmarks/threads.md``). The cost is memory: what a step freed stays resident
    (the default ``nsd-run`` peaked at 1.17 GB instead of 0.95); :func:`trim_heap` still
    gives it back when a long streaming run asks. Returns False where the C library is not
    glibc (nothing changed). Idempotent.
    """
    libc = _libc()
    if libc is None:
        return False
    return bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_KEEP)) and bool(
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)
    )


def trim_heap() -> None:
    """Give freed heap memory back to the OS (glibc ``malloc_trim``; a no-op elsewhere).

    Called after every batch: without it, allocator fragmentation lets the
    resident size of a long export creep up for its first ~1,000 frames
    (``docs/benchmarks/export.md``).
    """
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


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
