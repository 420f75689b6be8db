"""Which frames of a scene a job processes, and how to decode them one at a time.

A selection is written in a config as one of::

    frames: all                              # every frame
    frames: {start: 100, stop: 400, step: 2} # a range (stop exclusive, null: to the end)
    frames: [0, 10, 20]                      # a list of frame indices

:func:`select_frames` turns it into sorted, unique frame indices;
:func:`iter_selected` decodes them in order at the footage's native size,
holding one frame per camera at a time. Contiguous ranges and any selection of
video footage are decoded sequentially (skipped frames are decoded and
dropped, which is faster than seeking in a compressed video); other selections
of image folders read only the selected files.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from nsd.core.errors import ConfigError
from nsd.io.footage import MultiViewFootage

__all__ = ["iter_selected", "select_frames"]


def _int(value: Any, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"frames.{key} must be an integer, got {value!r}")
    return int(value)


def select_frames(spec: Any, num_frames: int) -> np.ndarray:
    """Frame indices (sorted, unique, int64) of a selection in a footage of ``num_frames``.

    Args:
        spec: ``"all"``, a mapping with ``start``/``stop``/``step`` (any may be
            missing or null), or a sequence of frame indices.
        num_frames: frames in the footage.

    Raises:
        ConfigError: unknown form, an index out of range, or an empty selection.

    Example:
        >>> select_frames({"start": 2, "stop": 9, "step": 3}, 10).tolist()
        [2, 5, 8]
        >>> select_frames([4, 1, 4], 10).tolist()
        [1, 4]
    """
    if isinstance(spec, str):
        if spec != "all":
            raise ConfigError(f"frames must be 'all', a range or a list, got {spec!r}")
        idx = np.arange(num_frames)
    elif isinstance(spec, Mapping):
        unknown = set(spec) - {"start", "stop", "step"}
        if unknown:
            raise ConfigError(f"frames: unknown keys {sorted(unknown)} (use start, stop, step)")
        start = 0 if spec.get("start") is None else _int(spec["start"], "start")
        stop = num_frames if spec.get("stop") is None else _int(spec["stop"], "stop")
        step = 1 if spec.get("step") is None else _int(spec["step"], "step")
        if step < 1:
            raise ConfigError(f"frames.step must be >= 1, got {step}")
        if not 0 <= start < num_frames:
            raise ConfigError(f"frames.start={start} is outside the footage's 0..{num_frames - 1}")
        idx = np.arange(start, min(stop, num_frames), step)
    elif isinstance(spec, Sequence):
        idx = np.unique(np.asarray([_int(t, f"[{i}]") for i, t in enumerate(spec)], np.int64))
        bad = idx[(idx < 0) | (idx >= num_frames)]
        if len(bad):
            raise ConfigError(
                f"frames {bad.tolist()} are outside the footage's 0..{num_frames - 1}"
            )
    else:
        raise ConfigError(f"frames must be 'all', a range or a list, got {spec!r}")
    if len(idx) == 0:
        raise ConfigError(f"frames={spec!r} selects no frame of a footage of {num_frames}")
    return idx.astype(np.int64)


def iter_selected(
    footage: MultiViewFootage, frames: np.ndarray
) -> Iterator[tuple[int, list[np.ndarray]]]:
    """``(t, views)`` for the selected frames in order, at the native size of each camera.

    Views are RGB uint8 (H_v, W_v, 3); cameras may differ in size, so they are
    returned as a list, not stacked.
    """
    frames = np.asarray(frames, np.int64)
    if len(frames) == 0:
        return
    contiguous = bool(np.all(np.diff(frames) == 1))
    if footage.random_access and not contiguous:
        for t in frames.tolist():
            yield t, [s.read(t) for s in footage.sources]
        return
    start, stop = int(frames[0]), int(frames[-1]) + 1
    streams = [s.iter_range(start, stop) for s in footage.sources]
    wanted = iter(frames.tolist())
    nxt = next(wanted)
    for t in range(start, stop):
        views = [next(it) for it in streams]
        if t == nxt:
            yield t, views
            nxt = next(wanted, None)
