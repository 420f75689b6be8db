"""A scene's training frames decoded once into a file on disk and read through a memory map.

Training reads random frames of the whole recording many times; holding them in the
process (the former ``(T, V, 3, H, W)`` tensor) made memory grow with the recording: 30
minutes of 4 cameras at 128 x 128 is about 10 GB. The store decodes the footage once,
streaming (one instant in memory at a time), into ``<cache>/frames/<key>.u8`` laid out
``(T, V, H, W, 3)`` uint8, and reads it through ``numpy.memmap``: the operating system
keeps the pages that are used and drops the others, so the process's own memory stays
flat in the number of frames. The key is the footage's signature (files, sizes, times),
the training size and the frame count, so changed footage is decoded again; a store is
complete only once its ``.json`` record is written (an interrupted decode starts over).
Where the cache folder cannot be written, frames are held in memory as before (said).

The cameras are decoded side by side, one forked process per camera up to one per core
(:class:`nsd.core.processes.BatchPool`): each decodes its camera in order from its first
frame (exact for every video, whatever its timeline) and writes its slice ``[:, v]`` of the
file, so the result does not depend on the number of processes (a test compares the files).
Decoding and resizing HD footage is most of a first run's waiting on a big scene
(docs/benchmarks/frame_store.md).

Indexing returns torch uint8 tensors in the layout the model reads: ``store[t]`` is
``(V, 3, H, W)``, ``store[t_idx, v_idx]`` ``(n, 3, H, W)``.

Per-frame results as large as the frames (the visual hull's pixel owners) go to a
:func:`scratch_array` next to the store: a memory map of an unnamed file that is deleted
when the process ends, so they do not grow the process's own memory either.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from nsd.core.atomic import atomic_write_text
from nsd.core.processes import BatchPool, resolve_workers
from nsd.io.footage import MultiViewFootage

__all__ = ["FrameStore", "scratch_array"]

log = logging.getLogger(__name__)


class FrameStore:
    """Frames ``0, stride, 2 stride, .. < stop`` of ``footage`` at its training size
    (module docstring); ``store[i]`` is footage frame ``i * stride``.

    Args:
        footage: the scene's footage, resized to the training size.
        stop: frames of the footage to cover.
        stride: keep every this many frames (decoding still reads them all, in order).
        workers: processes decoding the cameras side by side (0: one per available core,
            at most one per camera; 1: this process alone).
    """

    def __init__(self, footage: MultiViewFootage, stop: int, stride: int = 1,
                 workers: int = 0) -> None:
        V = footage.num_views
        H, W = footage.rig[0].size[1], footage.rig[0].size[0]
        self.stride = int(stride)
        if self.stride < 1:
            raise ValueError(f"frame stride must be >= 1, got {stride}")
        self.shape_thwc = (len(range(0, int(stop), self.stride)), V, H, W, 3)
        sig = "|".join(s.signature() for s in footage.sources)
        key = hashlib.sha1(f"{sig}|{W}x{H}|{stop}|{self.stride}".encode()).hexdigest()[:16]
        folder = footage.cache_dir / "frames"
        self.path = folder / f"{key}.u8"
        record = self.path.with_suffix(".json")
        self._array: np.ndarray
        try:
            if not (record.is_file() and self.path.is_file()
                    and self.path.stat().st_size == int(np.prod(self.shape_thwc))):
                folder.mkdir(parents=True, exist_ok=True)
                self._decode(footage, stop, workers)
                log.info("decoded %d frames of %s into %s", self.shape_thwc[0], footage.scene,
                         self.path)
                atomic_write_text(record, json.dumps({"shape": list(self.shape_thwc),
                                                      "cameras": footage.camera_names}))
            self._array = np.memmap(self.path, np.uint8, "r", shape=self.shape_thwc)
        except OSError as e:
            log.warning("frames of %s held in memory (cannot write %s: %s)", footage.scene,
                        folder, e)
            self._array = np.stack([v for t, v in footage.iter_frames(0, stop)
                                    if t % self.stride == 0])

    def _decode(self, footage: MultiViewFootage, stop: int, workers: int) -> None:
        """Decode into a temporary file next to the store, a camera per process, then move it
        into place."""
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        np.memmap(tmp, np.uint8, "w+", shape=self.shape_thwc).flush()  # the file, full size
        try:
            n = min(footage.num_views, resolve_workers("auto", workers, "cpu"))
            with BatchPool(lambda v: self._decode_view(footage, v, stop, tmp), n, n,
                           job="frame decoding", remedy="threads=") as pool:
                for _ in pool.map(range(footage.num_views)):
                    pass
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)

    def _decode_view(self, footage: MultiViewFootage, v: int, stop: int, file: Path) -> None:
        """Camera ``v``'s frames into its slice ``[:, v]`` of ``file``."""
        out = np.memmap(file, np.uint8, "r+", shape=self.shape_thwc)
        for t, img in enumerate(footage.iter_view(v, 0, stop)):
            if t % self.stride == 0:
                out[t // self.stride, v] = img
        out.flush()
        del out

    @property
    def shape(self) -> tuple[int, int, int, int, int]:
        """(T, V, 3, H, W), the layout of what indexing returns."""
        T, V, H, W, C = self.shape_thwc
        return T, V, C, H, W

    def __len__(self) -> int:
        return self.shape_thwc[0]

    def __getitem__(self, index: Any) -> Tensor:
        if not isinstance(index, tuple):
            index = (index,)
        index = tuple(i.numpy() if isinstance(i, Tensor) else i for i in index)
        arr = np.ascontiguousarray(self._array[index])  # (..., H, W, 3), read from the file
        if not arr.flags.writeable:  # a view of the read-only map (basic indexing): a copy, so
            arr = arr.copy()  # that a caller writing into the tensor cannot touch the file
        return torch.from_numpy(arr).movedim(-1, -3)


def scratch_array(folder: Path, shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """A zero-filled writable array of ``shape`` backed by an unnamed file in ``folder``
    (deleted when the array is gone), or in memory where ``folder`` cannot be written.

    Its pages belong to the file, not to the process's anonymous memory: the operating
    system writes them out and drops them under pressure.
    """
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder) as f:  # the map keeps the file open
            return np.memmap(f, dtype, "w+", shape=shape)
    except OSError as e:
        log.warning("%s held in memory (cannot write %s: %s)",
                    "x".join(map(str, shape)), folder, e)
        return np.zeros(shape, dtype)
