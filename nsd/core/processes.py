"""Work shared out to forked processes, taken back in order by this one (:class:`BatchPool`).

Used where the work is NumPy or torch on one core per item and the items are independent:
the export's batches (:mod:`nsd.export.subjects`), the keypoints' subject-frames
(:mod:`netepu.pipeline.subject_keypoints`), and a camera per item: each camera's background
estimate (:meth:`nsd.io.footage.MultiViewFootage.background_estimates`), its decoding into
the frame store (:mod:`nsd.io.frame_store`) and the scene check's sampled frames
(:mod:`nsd.io.scene_check`).

*The export*: a profile of ``nsd-export`` on one core (default scene) puts ~80 % of its
time in :func:`nsd.inference.multiview.decompose_views`, and half of that is not torch (the
visual hull's proposals and pixel owners are NumPy on one core), so more torch threads buy
little (1.32x on two cores). Batches are independent until tracking links them (the hull's
clustering, which carries its Gaussians from instant to instant, runs in the parent and
hands each batch its labels: :meth:`nsd.export.writer.SubjectWriter.hull_clusters`), so
each batch is decomposed by the next free one of ``P`` workers (forked processes with
``threads // P`` torch threads each) and the parent takes the results back in order,
tracks and writes. At most ``2 P`` batches are in flight, so memory stays flat in the
footage's length. A worker that dies (the out-of-memory killer) stops the work with a
message, not a wait.

``workers: auto`` (conf/export.yaml) is one process per available core up to
:data:`MAX_AUTO_WORKERS`, and 1 (this process alone) on a GPU or where processes cannot be
forked. The output does not depend on ``workers`` (a test compares the files).
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import cv2

from nsd.core.errors import ConfigError
from nsd.core.memory import peak_rss_mb
from nsd.core.threads import available_cores, set_threads

__all__ = ["MAX_AUTO_WORKERS", "BatchPool", "resolve_workers"]

MAX_AUTO_WORKERS = 8  # workers: auto uses at most this many processes (each holds the model)
_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_TASK: Callable[[Any], Any] | None = None  # the forked workers' function (set before the fork)


def resolve_workers(setting: Any, threads: int, device: str) -> int:
    """``workers``: a number >= 1 as given, or ``auto``: one per available core (``threads``
    when that is set), at most :data:`MAX_AUTO_WORKERS`; 1 on a GPU or without ``fork``.

    Example:
        >>> resolve_workers(3, 0, "cpu")
        3
        >>> resolve_workers("auto", 1, "cpu")
        1
        >>> resolve_workers("auto", 4, "cuda")
        1
    """
    forkable = "fork" in mp.get_all_start_methods() and sys.platform.startswith("linux")
    if setting == "auto":
        if device != "cpu" or not forkable:
            return 1
        return max(1, min(threads or available_cores(), MAX_AUTO_WORKERS))
    try:
        n = int(setting)
    except (TypeError, ValueError):
        raise ConfigError(f"workers: a number >= 1 or auto, got {setting!r}") from None
    if n < 1:
        raise ConfigError(f"workers: a number >= 1 or auto, got {setting!r}")
    if n > 1 and (device != "cpu" or not forkable):
        raise ConfigError(f"workers={n} needs a CPU device on Linux (forked processes); "
                          f"this run is on {device!r} on {sys.platform}: use workers=1")
    return n


def _start(threads: int, parent: int) -> None:
    """A worker's start: its own torch threads; Ctrl-C and SIGTERM are the parent's to handle
    (it stops the pool), and the worker dies with its parent (a killed export leaves no
    process behind: Linux's parent-death signal)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (AttributeError, OSError):  # a C library without prctl: workers end with the queue
        pass
    if os.getppid() != parent:  # the parent died before the line above
        os._exit(1)
    set_threads(threads)


def _run(item: Any) -> tuple[Any, float]:
    assert _TASK is not None
    return _TASK(item), peak_rss_mb()


class BatchPool:
    """``map(items)``: ``function(item)`` for each item, in order, by ``workers`` processes.

    With ``workers == 1`` the function runs in this process. Use as a context manager: the
    workers are stopped on leaving it, also on an error or an interrupt.

    Args:
        function: the work of one item; inherited by the forked workers, not pickled.
        workers: processes (see :func:`resolve_workers`).
        threads: torch threads shared by the workers (each gets ``threads // workers``).
        job, remedy: what the workers do and what to lower when one dies, for the message.
    """

    def __init__(self, function: Callable[[Any], Any], workers: int, threads: int,
                 job: str = "export", remedy: str = "workers= or batch_size=") -> None:
        self.function, self.workers = function, int(workers)
        self.job, self.remedy = job, remedy
        self.worker_threads = max(1, int(threads) // self.workers)
        self.worker_peak_mb = 0.0  # the largest peak resident size of one worker
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> BatchPool:
        global _TASK
        if self.workers > 1:
            _TASK = self.function
            # OpenCV's threads are set before the fork, which the workers inherit (set in a
            # forked worker, it waits for the parent's pool threads, which are not there)
            cv2_threads = cv2.getNumThreads()
            cv2.setNumThreads(self.worker_threads)
            try:
                self._pool = ProcessPoolExecutor(
                    self.workers, mp.get_context("fork"), initializer=_start,
                    initargs=(self.worker_threads, os.getpid()))
                self._pool.submit(int).result()  # forks every worker now
            except BaseException:
                self.__exit__(None, None, None)
                raise
            finally:
                cv2.setNumThreads(cv2_threads)
        return self

    def __exit__(self, kind, value, tb) -> None:
        """Stop the workers: the queued batches are dropped, running ones finish (a batch)."""
        global _TASK
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        _TASK = None

    def map(self, items: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """``(item, function(item))`` in the items' order; at most ``2 workers`` items are
        held at a time."""
        if self._pool is None:
            for item in items:
                yield item, self.function(item)
            return
        pending: deque = deque()
        for item in items:
            try:  # a pool whose worker died refuses new items as it fails pending ones
                future = self._pool.submit(_run, item)
            except BrokenProcessPool:
                raise self._died() from None
            pending.append((item, future))
            if len(pending) >= 2 * self.workers:
                yield self._take(pending)
        while pending:
            yield self._take(pending)

    def _died(self) -> RuntimeError:
        return RuntimeError(
            f"{self.job}: a worker process died (killed by the system, e.g. out of memory, "
            f"with {self.workers} workers): lower {self.remedy}")

    def _take(self, pending: deque) -> tuple[Any, Any]:
        item, future = pending.popleft()
        try:
            result, peak = future.result()
        except BrokenProcessPool:
            raise self._died() from None
        self.worker_peak_mb = max(self.worker_peak_mb, peak)
        return item, result
