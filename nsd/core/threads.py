"""How many CPU threads torch uses: by default every core this process may run on.

``threads: 0`` in a command's config means every core of the machine that the process may
use (its CPU affinity, so ``taskset`` and container limits count), divided among the
processes of a torchrun job on this node; a positive value is used as given. Setting them
also keeps freed heap pages in the process (:func:`nsd.core.memory.keep_freed_heap`), since
every command that sets threads runs torch steps that free and re-allocate the same tensors.
"""

from __future__ import annotations

import logging
import os

import torch

from nsd.core.memory import keep_freed_heap

__all__ = ["available_cores", "set_threads"]

log = logging.getLogger(__name__)


def available_cores() -> int:
    """Cores this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def set_threads(threads: int) -> int:
    """Set torch's intra-op threads: ``threads`` > 0 as given, 0 for every available core
    (shared among a torchrun job's local processes), and keep freed heap pages. Returns the
    number of threads set.

    Example:
        >>> before = torch.get_num_threads()
        >>> set_threads(1)
        1
        >>> _ = set_threads(before)
    """
    if threads < 0:
        raise ValueError(f"threads must be >= 0 (0: every core), got {threads}")
    n = threads or max(1, available_cores() // int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
    torch.set_num_threads(n)
    keep_freed_heap()
    return n
