"""One camera's frames: a video file or a folder of images.

Frame ``t`` of a camera is its ``t``-th frame: the ``t``-th image in natural name order, or
a video's ``t``-th instant (read frame-exactly also where OpenCV's seek is not, a frame the
camera dropped filled with the one before: :class:`VideoSource`). Frames are RGB ``uint8``
arrays, (H, W, 3). The cameras of a scene together: :mod:`nsd.io.footage`.
"""

from __future__ import annotations

import functools
import itertools
import logging
import os
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from nsd.core.errors import FootageError

__all__ = [
    "ESTIMATED_COUNT",
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "FrameSource",
    "ImageFolderSource",
    "VideoSource",
    "find_source",
]

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
# a video's first frames whose times are compared when it is opened (variable frame rate)
TIMELINE_PROBE = 32
# containers without a frame count (OpenCV estimates it from the duration, so a dropped
# frame's gap counts as a frame): every frame's time is read when they are opened
ESTIMATED_COUNT = (".mkv", ".webm", ".mpg", ".mpeg")


def _natural_key(p: Path) -> list:
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", p.name)]


class FrameSource(ABC):
    """The frames of one camera."""

    camera: str
    path: Path
    notes: tuple[str, ...] = ()  # what the user should know about this camera's footage

    @property
    @abstractmethod
    def num_frames(self) -> int: ...

    @property
    @abstractmethod
    def size(self) -> tuple[int, int]:
        """Native frame size (width, height)."""

    @abstractmethod
    def read(self, t: int) -> np.ndarray:
        """Frame ``t`` as RGB uint8 (H, W, 3)."""

    @abstractmethod
    def iter_range(self, start: int, stop: int) -> Iterator[np.ndarray]:
        """Frames ``start .. stop-1`` in order (sequential decoding)."""

    def iter_frames(self, ts: Sequence[int]) -> Iterator[np.ndarray]:
        """Frames ``ts`` (increasing, repeats allowed) in order, RGB uint8 (H, W, 3) each:
        a sample of a long recording, read without holding it."""
        for t in ts:
            yield self.read(int(t))

    def signature(self) -> str:
        """Changes when the footage changes (for cache keys)."""
        st = self.path.stat()
        return f"{self.path.resolve()}:{st.st_size}:{st.st_mtime_ns}:{self.num_frames}"

    def _error(self, what: str, t: int | None = None) -> FootageError:
        frame = "" if t is None else f", frame {t}"
        return FootageError(f"camera '{self.camera}' ({self.path}{frame}): {what}")


class VideoSource(FrameSource):
    """A video file read with OpenCV.

    Frame ``t`` is the ``t``-th instant of the camera's constant frame rate. OpenCV seeks to
    a frame number through its time (``t / fps``), which is frame-exact only when the frames
    are evenly spaced in time: the file's timeline is probed when it is opened (the first
    ``TIMELINE_PROBE`` frame times and the last frame's; every frame's time in a container
    without a frame count, ``ESTIMATED_COUNT``, and wherever the probe finds the times
    uneven). Where the timeline is regular except for instants without a frame (the camera
    dropped them), each missing frame is filled with the frame before it, so that frame
    ``t`` stays the other cameras' instant ``t``; a timeline of uneven times (variable
    frame rate) gives frame ``t`` as the ``t``-th frame the decoder returns. Either is read
    in order from the start instead of seeking, with a warning naming the camera and file.
    """

    def __init__(self, camera: str, path: str | os.PathLike) -> None:
        self.camera, self.path = camera, Path(path)
        if not self.path.is_file():
            raise self._error("video file does not exist")
        notes: list[str] = []
        # (num_frames,) the decoded frame shown at each instant, where frames were dropped
        self._frame_of: np.ndarray | None = None
        estimated = self.path.suffix.lower() in ESTIMATED_COUNT
        cap = self._open()
        try:
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            ok, first = cap.read()
            if not ok:
                raise self._error("video has zero readable frames")
            times = [cap.get(cv2.CAP_PROP_POS_MSEC)]
            while len(times) < TIMELINE_PROBE and cap.grab():
                times.append(cap.get(cv2.CAP_PROP_POS_MSEC))
            self.seekable, step, drift, why = _even_timeline(np.asarray(times))
            why = "" if self.seekable else why
            whole = None  # every frame's time (ms), where the count or the probe is not enough
            if n <= 0 or not self.seekable or estimated:
                whole = self._timeline()
            elif n > 1:
                last = self._landed(cap, n - 1)
                if last is None:  # the container over-claims (an edit list)
                    claimed, n = n, self._decodable(cap, n)
                    notes.append(f"the container claims {claimed} frames but only {n} "
                                 f"decode; using those {n}")
                # uneven later on (a time before the first frame's: the container keeps no
                # usable times after a seek, e.g. H.264 in AVI; nothing to compare)
                elif last >= times[0] and (abs(last - times[0] - (n - 1) * step)
                                           > step / 4 + (n - 1) * drift):
                    self.seekable = False
                    why = (f"frame {n - 1} is at {last - times[0]:.0f} ms, not at "
                           f"{(n - 1) * step:.0f} ms as a constant rate puts it")
                    whole = self._timeline()
            if whole is not None:
                claimed, n = n, len(whole)
                if claimed > 0 and claimed != n and not estimated:
                    notes.append(f"the container claims {claimed} frames but {n} decode; "
                                 f"using those {n}")
                slots, step, start, uneven = _frame_slots(whole)
                if slots is None:
                    self.seekable, why = False, why or uneven
                elif slots[-1] != n - 1:  # instants without a frame: dropped
                    self.seekable = False
                    instants = np.arange(slots[-1] + 1)
                    self._frame_of = np.searchsorted(slots, instants, side="right") - 1
                    notes.append(_dropped(whole[0], step, start,
                                          np.setdiff1d(instants, slots)))
                    n = len(instants)
                elif self.seekable and n > 1 and step > 0:  # even: does the seek find them?
                    last = self._landed(cap, n - 1)
                    if last is None or abs(last - whole[-1]) > step / 4:
                        self.seekable = False
                        notes.append(_astray(last, whole, step, cap.get(cv2.CAP_PROP_FPS)))
            if not self.seekable and self._frame_of is None:
                notes.append(
                    f"variable frame rate ({why}); OpenCV cannot seek in it frame-exactly, "
                    "so its frames are decoded in order from the start (slower where a "
                    "frame is asked alone). Its frame t is the t-th frame it holds: if the "
                    "camera dropped frames, it is out of step with the others after the "
                    "drop. Re-encoding at a constant frame rate (ffmpeg's -fps_mode cfr) "
                    "avoids both")
        finally:
            cap.release()
        self._n, self._size = n, (first.shape[1], first.shape[0])
        self.notes = tuple(f"camera '{camera}' ({self.path}): {note}" for note in notes)
        for note in self.notes:
            log.warning("%s", note)

    def _timeline(self) -> np.ndarray:
        """Every frame's time (ms, (frames that decode,)), by decoding from the start (once
        per file and process)."""
        st = self.path.stat()
        return _decoded_times(str(self.path), st.st_size, st.st_mtime_ns)

    @staticmethod
    def _landed(cap: cv2.VideoCapture, t: int) -> float | None:
        """The time (ms) of the frame a seek to frame ``t`` decodes; None if none does."""
        cap.set(cv2.CAP_PROP_POS_FRAMES, t)
        return cap.get(cv2.CAP_PROP_POS_MSEC) if cap.read()[0] else None

    def _decodable(self, cap: cv2.VideoCapture, claimed: int) -> int:
        """Frames that decode when frame ``claimed - 1`` does not: a binary search for the
        last decodable frame (frame 0 decodes)."""
        lo, hi = 0, claimed - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if self._landed(cap, mid) is not None else (lo, mid)
        return lo + 1

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise self._error("OpenCV cannot open this video (corrupt file or unknown codec)")
        return cap

    def _seek(self, t: int) -> cv2.VideoCapture:
        """An open capture whose next frame is frame ``t`` (a seekable video)."""
        cap = self._open()
        if t > 0:
            cap.set(cv2.CAP_PROP_POS_FRAMES, t)
        return cap

    def _skip(self, cap: cv2.VideoCapture, current: int, to: int) -> int:
        """Grab frames of ``cap``, whose last grabbed frame is ``current``, up to frame ``to``
        (decoding in order); returns ``to``."""
        while current < to:
            if not cap.grab():
                raise self._error("frame cannot be decoded (truncated or corrupt video)",
                                  current + 1)
            current += 1
        return current

    def _in_order(self, ts: Sequence[int]) -> Iterator[np.ndarray]:
        """Frames ``ts`` (increasing, repeats allowed), decoded in order from the start."""
        ts = [int(t) for t in ts]
        bad = [t for t in ts if not 0 <= t < self._n]
        if bad:
            raise self._error(f"frame index out of range 0..{self._n - 1}", bad[0])
        if any(b < a for a, b in itertools.pairwise(ts)):
            raise ValueError(f"iter_frames needs frames in increasing order, got {ts}")
        cap, last = self._open(), [-1]  # the last frame grabbed

        def grab(t: int) -> tuple[bool, np.ndarray | None]:
            last[0] = self._skip(cap, last[0],
                                 t if self._frame_of is None else int(self._frame_of[t]))
            return cap.retrieve()
        return self._decoded(cap, ts, grab)

    def _decoded(self, cap: cv2.VideoCapture, ts: Sequence[int],
                 get: Callable[[int], tuple[bool, np.ndarray | None]]) -> Iterator[np.ndarray]:
        """Frames ``ts`` as RGB, ``get(t)`` decoding frame ``t`` from ``cap`` (released at
        the end)."""
        try:
            for t in ts:
                ok, frame = get(t)
                if not ok:
                    raise self._error("frame cannot be decoded (truncated or corrupt video)", t)
                yield cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        finally:
            cap.release()

    @property
    def num_frames(self) -> int:
        return self._n

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def read(self, t: int) -> np.ndarray:
        if not 0 <= t < self._n:
            raise self._error(f"frame index out of range 0..{self._n - 1}", t)
        return next(self.iter_range(t, t + 1))

    def iter_frames(self, ts: Sequence[int]) -> Iterator[np.ndarray]:
        if self.seekable:
            yield from super().iter_frames(ts)
        else:
            yield from self._in_order(ts)

    def iter_range(self, start: int, stop: int) -> Iterator[np.ndarray]:
        if not self.seekable:
            yield from self._in_order(range(start, stop))
            return
        cap = self._seek(start)
        yield from self._decoded(cap, range(start, stop), lambda t: cap.read())


@functools.lru_cache(maxsize=64)
def _decoded_times(path: str, size: int, mtime_ns: int) -> np.ndarray:
    """The time (ms) of every frame of the video at ``path`` that decodes, in order,
    ((frames,), read-only); ``size`` and ``mtime_ns`` key the cache to the file's contents."""
    cap, times = cv2.VideoCapture(path), []
    try:
        while cap.grab():
            times.append(cap.get(cv2.CAP_PROP_POS_MSEC))
    finally:
        cap.release()
    out = np.asarray(times, dtype=np.float64)
    out.setflags(write=False)
    return out


def _timeless(gaps: np.ndarray) -> bool:
    """Whether frame-time gaps ``gaps`` (ms, (K-1,)) say nothing: too few, not finite, or
    not increasing (a container without times)."""
    return len(gaps) < 2 or not np.all(np.isfinite(gaps)) or np.median(gaps) <= 0


def _rate_line(instants: np.ndarray, times: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The constant rate through frame times ``times`` (ms, (K,)) at ``instants`` ((K,)):
    (frame interval in ms, time of instant 0, residuals (K,)), and whether the times lie on
    it: every one within a tenth of a frame (at least 1.5 ms: times rounded to the
    millisecond) is ``np.abs(residual).max() <= _tolerance(step)``."""
    step, start = np.polyfit(instants, times, 1)
    return float(step), float(start), times - (start + step * instants)


def _tolerance(step: float) -> float:
    """How far (ms) a frame time may lie off a constant rate of interval ``step`` (ms)."""
    return max(step / 10, 1.5)


def _frame_slots(times: np.ndarray) -> tuple[np.ndarray | None, float, float, str]:
    """The instant of each frame on one constant rate: frame times ``times`` (ms, (K,)) as
    whole numbers of frame intervals from the first. Returns (instants ((K,) increasing
    int64), frame interval (ms), time of instant 0 (ms), "") where every time lies on a
    line through them (:func:`_rate_line`); (None, 0, 0, how the times are uneven) where
    they do not (variable frame rate). A gap of about two intervals is one instant without
    a frame. Times that do not increase (a container without them) are the frames' own
    numbers: nothing says otherwise.
    """
    gaps = np.diff(times)
    if _timeless(gaps):
        return np.arange(len(times)), 0.0, 0.0, ""
    whole = np.rint(gaps / np.median(gaps))
    slots = np.r_[0, np.cumsum(whole)].astype(np.int64)
    why = f"its frames are {gaps.min():.0f}-{gaps.max():.0f} ms apart"
    if whole.min() < 1:
        return None, 0.0, 0.0, why
    step, start, residual = _rate_line(slots, times)
    off = np.abs(residual).max()
    if off > _tolerance(step):
        return None, 0.0, 0.0, f"{why}, up to {off:.0f} ms off one constant rate"
    return slots, step, start, ""


def _astray(landed: float | None, times: np.ndarray, step: float, fps: float) -> str:
    """The warning about a video of frame times ``times`` (ms, (K,)) evenly ``step`` ms
    apart in which OpenCV's seek to the last frame lands at ``landed`` (ms; None: on no
    frame), going by the rate ``fps`` the file declares."""
    where = "on no frame" if landed is None else f"at {landed - times[0]:.0f} ms"
    return (f"OpenCV's seek is not frame-exact in it: a seek to its last frame, "
            f"{len(times) - 1}, lands {where}, not at {times[-1] - times[0]:.0f} ms (the "
            f"file declares {fps:.3f} fps, its frames come every {step:.1f} ms), so its "
            "frames are decoded in order from the start (slower where a frame is asked "
            "alone)")


def _dropped(first: float, step: float, start: float, missing: np.ndarray) -> str:
    """The warning about the instants ``missing`` without a frame in a timeline of one frame
    every ``step`` ms from ``start`` (ms), the first frame at ``first`` (ms)."""
    shown = ", ".join(f"{m} ({start + m * step - first:.0f} ms)" for m in missing[:5])
    more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
    return (f"{len(missing)} frame(s) missing from its timeline of one frame every "
            f"{step:.1f} ms: frame(s) {shown}{more} (the camera dropped them). Each is "
            "filled with the frame before it, so that frame t stays the other cameras' "
            "instant t; the video is decoded in order from the start (slower where a frame "
            "is asked alone)")


def _even_timeline(times: np.ndarray) -> tuple[bool, float, float, str]:
    """Whether frame times ``times`` (ms, (K,)) lie on one constant rate (:func:`_rate_line`),
    and what it is: OpenCV's seek, which finds frame ``t`` at ``t / fps``, is then exact.
    Returns (even, frame interval in ms, three standard errors of that interval: how far a
    later frame may drift per frame from the line without saying anything, how the times
    are uneven). Times that do not increase (a container without them) count as even:
    nothing says otherwise.
    """
    k = np.arange(len(times), dtype=np.float64)
    gaps = np.diff(times)
    if _timeless(gaps):
        return True, 0.0, 0.0, ""
    step, _, residual = _rate_line(k, times)
    se = float(np.sqrt(residual @ residual / (len(k) - 2) / ((k - k.mean()) ** 2).sum()))
    even = bool(np.abs(residual).max() <= _tolerance(step))
    return even, step, 3 * se, (f"its first {len(times)} frames are {gaps.min():.0f}-"
                                f"{gaps.max():.0f} ms apart")


class ImageFolderSource(FrameSource):
    """A folder of images, one per frame, sorted in natural order (or the given ``files``)."""

    def __init__(self, camera: str, path: str | os.PathLike,
                 files: Sequence[Path] | None = None) -> None:
        self.camera, self.path = camera, Path(path)
        if not self.path.is_dir():
            raise self._error("image folder does not exist")
        self.files = list(files) if files is not None else sorted(
            (p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS),
            key=_natural_key,
        )
        if not self.files:
            raise self._error(f"image folder holds no images ({', '.join(IMAGE_EXTENSIONS)})")
        self._size: tuple[int, int] | None = None

    @property
    def num_frames(self) -> int:
        return len(self.files)

    @property
    def size(self) -> tuple[int, int]:
        if self._size is None:
            first = self.read(0)
            self._size = (first.shape[1], first.shape[0])
        return self._size

    def read(self, t: int) -> np.ndarray:
        if not 0 <= t < len(self.files):
            raise self._error(f"frame index out of range 0..{len(self.files) - 1}", t)
        img = cv2.imread(str(self.files[t]), cv2.IMREAD_COLOR)
        if img is None:
            raise FootageError(
                f"camera '{self.camera}' ({self.files[t]}, frame {t}): image cannot be read"
            )
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    def iter_range(self, start: int, stop: int) -> Iterator[np.ndarray]:
        for t in range(start, stop):
            yield self.read(t)

    def signature(self) -> str:
        last = self.files[-1].stat()
        return f"{self.path.resolve()}:{len(self.files)}:{last.st_size}:{last.st_mtime_ns}"


def find_source(scene: str | os.PathLike, camera: str) -> FrameSource:
    """The video or image folder of ``camera`` in a scene folder."""
    scene = Path(scene)
    for folder in (scene, scene / "videos", scene / "images"):
        d = folder / camera
        if d.is_dir():
            return ImageFolderSource(camera, d)
        for ext in VIDEO_EXTENSIONS:
            for cand in (folder / f"{camera}{ext}", folder / f"{camera}{ext.upper()}"):
                if cand.is_file():
                    return VideoSource(camera, cand)
    raise FootageError(
        f"camera '{camera}': no video ({scene}/{camera}.mp4 or another of "
        f"{', '.join(VIDEO_EXTENSIONS)}) and no image folder ({scene}/{camera}/); "
        "also looked in videos/ and images/"
    )
