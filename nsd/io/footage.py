"""Synchronised multi-view footage from a scene folder.

A scene folder holds one calibration file (see :mod:`nsd.cameras.calibration_io`) and,
for every camera named in it, either one video file (any container OpenCV
reads) or one folder of images (sorted by name, numbers in natural order)::

    scene/
      calibration.toml
      cam0.mp4            # or videos/cam0.mp4
      cam1/000000.png ... # or images/cam1/...

Frame ``t`` of every camera is taken to show the same instant. Frames are
returned as RGB ``uint8`` arrays, (H, W, 3) per view.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import read_calibration
from nsd.core.atomic import atomic_write_bytes, atomic_write_text
from nsd.core.errors import CalibrationError, ConfigError, FootageError
from nsd.core.processes import BatchPool, resolve_workers
from nsd.cues.background import BACKGROUND_METHODS, BackgroundEstimate, estimate_background
from nsd.io.frame_sources import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    FrameSource,
    ImageFolderSource,
    VideoSource,
    find_source,
)

__all__ = ["MultiViewFootage", "footage_frame_rate"]

log = logging.getLogger(__name__)

BACKGROUND_SAMPLES = 50  # frames in the per-camera median background (NSD: 50)
# the cached estimates' format (2: the stays in their own mask level; 3: only the stays kept
# in a subject-like colour)
BACKGROUND_CACHE = 3
# cameras whose frame counts differ by at most this many are trimmed to the shortest (with a
# warning: camera software often drops the last frame); a larger difference is an error
MAX_FRAME_TRIM = 10



def footage_frame_rate(scene: str | os.PathLike, cameras: Sequence[str]) -> float | None:
    """Frames per second of a scene's footage: the first video's own rate, else a synthetic
    scene's (``gt/scene.json``); None when nothing says (image folders, no footage)."""
    scene = Path(scene)
    for camera in cameras:
        try:
            source = find_source(scene, camera)
        except FootageError:  # no footage to ask (its reader says so where it is read)
            continue
        if not isinstance(source, ImageFolderSource):
            cap = cv2.VideoCapture(str(source.path))
            rate = cap.get(cv2.CAP_PROP_FPS)
            cap.release()
            if rate and np.isfinite(rate) and rate > 0:
                return float(rate)
    meta = scene / "gt" / "scene.json"
    if meta.is_file():
        rate = json.loads(meta.read_text()).get("fps")
        if rate:
            return float(rate)
    return None


class MultiViewFootage:
    """All cameras of a scene folder, frame-synchronised.

    Args:
        scene: the scene folder.
        cameras: names of the cameras to use (default: all in the calibration).
        image_size: (width, height) to resize every frame to; the rig's
            intrinsics are rescaled to match. Default: native size.
        cache_dir: where median backgrounds are cached (default ``<scene>/.cache``).
        calibration: the scene's calibration when the caller has read it already
            (default: read from the scene folder).
        units: the calibration file's length unit when it is read here
            (:mod:`nsd.cameras.units`).
        background: how a camera without a plate gets its background, one of
            :data:`nsd.cues.background.BACKGROUND_METHODS` (``data.background``).

    Attributes:
        calibration_names: every camera of the calibration file, in its order (the
            footage may use fewer).

    Raises:
        FootageError: a camera's footage is missing, unreadable or empty, or the
            cameras hold different numbers of frames.
        CalibrationError: the calibration is invalid or its image size disagrees
            with the footage.
    """

    def __init__(
        self,
        scene: str | os.PathLike,
        cameras: Sequence[str] | None = None,
        image_size: tuple[int, int] | None = None,
        cache_dir: str | os.PathLike | None = None,
        calibration: CameraRig | None = None,
        units: str = "auto",
        background: str = "median",
    ) -> None:
        if background not in BACKGROUND_METHODS:
            raise ConfigError(
                f"data.background must be one of {', '.join(BACKGROUND_METHODS)}, "
                f"got {background!r}")
        self.background_method = background
        self.scene = Path(scene)
        if not self.scene.is_dir():
            raise FootageError(f"scene folder {self.scene} does not exist")
        rig = calibration if calibration is not None else read_calibration(self.scene, units)
        self.calibration_names = list(rig.names)
        if cameras is not None:
            missing = [c for c in cameras if c not in rig.names]
            if missing:
                raise FootageError(
                    f"cameras {missing} are not in the calibration {rig.source} "
                    f"(it has {rig.names})"
                )
            rig = rig.select(list(cameras))
        self.sources = [find_source(self.scene, c.name) for c in rig]
        # what the user should know about the footage (logged too): the cameras' notes, a trim
        self.notes = [note for s in self.sources for note in s.notes]
        counts = [s.num_frames for s in self.sources]
        self._num_frames = min(counts)
        if max(counts) != min(counts):
            detail = ", ".join(f"'{s.camera}' ({s.path}): {s.num_frames}" for s in self.sources)
            if max(counts) - min(counts) > MAX_FRAME_TRIM:
                raise FootageError(f"cameras hold different numbers of frames: {detail}; "
                                   "they must show the same instants")
            trimmed = (f"cameras hold different numbers of frames ({detail}): the last frames "
                       f"of the longer ones are left out ({self._num_frames} frames used); "
                       "camera software often drops a frame at the end")
            log.warning("%s", trimmed)
            self.notes.append(trimmed)
        fixed = []
        for cam, src in zip(rig, self.sources, strict=True):
            if cam.size is None:
                cam = cam.with_size(src.size)
            elif tuple(cam.size) != tuple(src.size):
                raise CalibrationError(
                    f"camera '{cam.name}': calibration {rig.source} says image size "
                    f"{cam.size[0]}x{cam.size[1]} but {src.path} is {src.size[0]}x{src.size[1]}"
                )
            fixed.append(cam)
        self.native_rig = CameraRig(fixed, rig.source)
        self.image_size = tuple(image_size) if image_size is not None else None
        self.rig = self.native_rig.scaled(image_size) if image_size else self.native_rig
        self.cache_dir = Path(cache_dir) if cache_dir else self.scene / ".cache"

    # ------------------------------------------------------------------ basics
    @property
    def num_frames(self) -> int:
        """Frames every camera holds (the shortest camera's count)."""
        return self._num_frames

    @property
    def random_access(self) -> bool:
        """Every camera is an image folder: any frame is read alone, exactly (a video is
        decoded in order)."""
        return all(isinstance(s, ImageFolderSource) for s in self.sources)

    @property
    def num_views(self) -> int:
        return len(self.sources)

    @property
    def camera_names(self) -> list[str]:
        return self.rig.names

    def _resize(self, img: np.ndarray, view: int) -> np.ndarray:
        size = self.rig[view].size
        if size is None or (img.shape[1], img.shape[0]) == tuple(size):
            return img
        return cv2.resize(img, size, interpolation=cv2.INTER_AREA)

    def frame(self, t: int) -> np.ndarray:
        """All views of frame ``t``: uint8 (V, H, W, 3)."""
        self._check_t(t)
        return np.stack([self._resize(s.read(t), v) for v, s in enumerate(self.sources)])

    def _check_t(self, t: int) -> None:
        if not 0 <= t < self.num_frames:
            raise FootageError(f"{self.scene}: frame {t} out of range 0..{self.num_frames - 1}")

    def iter_frames(
        self, start: int = 0, stop: int | None = None
    ) -> Iterator[tuple[int, np.ndarray]]:
        """``(t, views)`` for frames ``start .. stop-1`` decoded sequentially.

        Only one frame per camera is held in memory at a time, so this streams
        footage of any length.
        """
        stop = self.num_frames if stop is None else min(stop, self.num_frames)
        its = [self.iter_view(v, start, stop) for v in range(self.num_views)]
        for t in range(start, stop):
            yield t, np.stack([next(it) for it in its])

    def iter_view(self, v: int, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        """Camera ``v``'s frames ``start .. stop-1`` at the footage's size, decoded in order:
        uint8 (H, W, 3) each."""
        stop = self.num_frames if stop is None else min(stop, self.num_frames)
        for img in self.sources[v].iter_range(start, stop):
            yield self._resize(img, v)

    def load(self, frames: Sequence[int] | None = None) -> np.ndarray:
        """Decode frames into memory: uint8 (T, V, H, W, 3) (all frames by default)."""
        if frames is None:
            return np.stack([views for _, views in self.iter_frames()])
        return np.stack([self.frame(int(t)) for t in frames])

    def sample_view_pairs(
        self, rng: np.random.Generator, n: int, frames: Sequence[int] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` random training pairs: frame indices t, view v and a different view w.

        Returns:
            three int64 arrays of shape (n,). ``v != w`` always; the order of the
            pair is random, so each camera serves as source and target.
        """
        if self.num_views < 2:
            raise FootageError(f"{self.scene}: view pairs need at least 2 cameras")
        pool = np.arange(self.num_frames) if frames is None else np.asarray(frames)
        t = rng.choice(pool, size=n)
        v = rng.integers(0, self.num_views, size=n)
        w = (v + rng.integers(1, self.num_views, size=n)) % self.num_views
        return t.astype(np.int64), v.astype(np.int64), w.astype(np.int64)

    # ------------------------------------------------------------------ background
    def background(self, num_samples: int = BACKGROUND_SAMPLES, workers: int = 0) -> np.ndarray:
        """Per-camera background: uint8 (V, H, W, 3), cached on disk.

        A background plate (:meth:`plate`) replaces the footage where the scene has one:
        then the median of the plate's frames. Otherwise the estimate of the footage's
        ``background`` method (:meth:`background_estimate`) from ``num_samples`` frames
        spread evenly over the sequence, computed at the native resolution and then
        resized. The cache is keyed by the footage's signature, so changed footage is
        recomputed. ``workers``: see :meth:`background_estimates`.
        """
        return np.stack([self._resize(est.image, v) for v, est in
                         enumerate(self.background_estimates(num_samples, workers))])

    def plate(self, v: int) -> FrameSource | None:
        """Camera ``v``'s background plate, if the scene has one: ``background/<camera>.<image>``
        (one picture of the empty arena), ``background/<camera>/`` (images) or
        ``background/<camera>.<video>`` (a short empty-arena clip).

        Raises:
            FootageError: the plate's size is not the footage's (the message names the file).
        """
        folder, src = self.scene / "background", self.sources[v]
        plate: FrameSource | None = None
        where: Path | None = None
        if folder.is_dir() and (folder / src.camera).is_dir():
            plate, where = ImageFolderSource(src.camera, folder / src.camera), folder / src.camera
        elif folder.is_dir():
            for p in sorted(folder.glob(f"{src.camera}.*")):
                if p.suffix.lower() in IMAGE_EXTENSIONS:
                    plate, where = ImageFolderSource(src.camera, folder, files=[p]), p
                    break
                if p.suffix.lower() in VIDEO_EXTENSIONS:
                    plate, where = VideoSource(src.camera, p), p
                    break
        if plate is not None and tuple(plate.size) != tuple(src.size):
            raise FootageError(
                f"camera '{src.camera}': background plate {where} is "
                f"{plate.size[0]}x{plate.size[1]} but the footage is {src.size[0]}x{src.size[1]}")
        return plate

    def native_background(self, v: int, num_samples: int = BACKGROUND_SAMPLES) -> np.ndarray:
        """Camera ``v``'s background at the footage's native resolution, uint8 (H, W, 3)
        (the plate or the estimate of :meth:`background_estimate`)."""
        return self.background_estimate(v, num_samples).image

    def background_estimates(
        self, num_samples: int = BACKGROUND_SAMPLES, workers: int = 0
    ) -> list[BackgroundEstimate]:
        """Every camera's :meth:`background_estimate`; those not cached are computed side by
        side by ``workers`` forked processes (0: one per available core, at most
        :data:`nsd.core.processes.MAX_AUTO_WORKERS`), one camera each: the estimate is NumPy
        on one core, seconds per camera at 512 x 512 (docs/benchmarks/background_cost.md)."""
        known = [self._cached_background(self._background_source(v, num_samples)[2])
                 for v in range(self.num_views)]  # each cache read once
        todo = [v for v, est in enumerate(known) if est is None]
        n = min(len(todo), resolve_workers("auto", workers, "cpu"))
        if n > 1:
            with BatchPool(lambda v: self.background_estimate(v, num_samples), n, n,
                           job="background estimate", remedy="threads=") as pool:
                for v, est in pool.map(todo):
                    known[v] = est
        return [est if est is not None else self.background_estimate(v, num_samples)
                for v, est in enumerate(known)]

    def _background_source(self, v: int, num_samples: int) -> tuple[FrameSource, str, Path]:
        """What camera ``v``'s background is estimated from (its plate, else its footage),
        by which method, and where the estimate is cached (keyed by the source's signature,
        the samples and the method)."""
        plate = self.plate(v)
        src = self.sources[v] if plate is None else plate
        method = "median" if plate is not None else self.background_method
        key = hashlib.sha1(f"{src.signature()}:{num_samples}:{method}:{BACKGROUND_CACHE}"
                           .encode()).hexdigest()[:16]
        return src, method, self.cache_dir / "background" / f"{src.camera}.{key}.png"

    @staticmethod
    def _cached_background(path: Path) -> BackgroundEstimate | None:
        """The background estimate cached at ``path``, or None (not cached, or unreadable)."""
        mask_path, meta_path = path.with_suffix(".uncertain.png"), path.with_suffix(".json")
        if not (path.is_file() and mask_path.is_file() and meta_path.is_file()):
            return None
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError):
            return None
        if img is None or mask is None:
            return None
        return BackgroundEstimate(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), mask >= 128,
                                  mask == 255, int(meta.get("samples", 0)), mask >= 224)

    def background_estimate(
        self, v: int, num_samples: int = BACKGROUND_SAMPLES
    ) -> BackgroundEstimate:
        """Camera ``v``'s background and its uncertain pixels at native resolution, cached
        on disk (keyed by the footage's signature and the method).

        With a plate (:meth:`plate`): the median of the plate's frames, nothing uncertain.
        Otherwise :func:`nsd.cues.background.estimate_background` with this footage's
        ``background`` method over ``num_samples`` frames spread evenly over the sequence.
        """
        src, method, path = self._background_source(v, num_samples)
        cached = self._cached_background(path)
        if cached is not None:
            return cached
        mask_path, meta_path = path.with_suffix(".uncertain.png"), path.with_suffix(".json")
        idx = np.unique(np.linspace(0, src.num_frames - 1, num_samples).round().astype(int))
        stack = np.stack(list(src.iter_frames(idx)))
        est = estimate_background(stack, method)
        if src is not self.sources[v]:  # a plate
            est.uncertain[:] = False
        try:
            ok, buf = cv2.imencode(".png", cv2.cvtColor(est.image, cv2.COLOR_RGB2BGR))
            # 255: uncertain, second colour taken (a stay); 224: a stay, first colour kept;
            # 192: uncertain, no stay
            mask = np.select([est.replaced, est.stayed, est.uncertain], [255, 224, 192],
                             0).astype(np.uint8)
            ok_mask, buf_mask = cv2.imencode(".png", mask)
            if ok and ok_mask:
                atomic_write_bytes(path, buf.tobytes())
                atomic_write_bytes(mask_path, buf_mask.tobytes())
                atomic_write_text(meta_path, json.dumps({
                    "source": str(src.path), "frames": idx.tolist(), "method": method,
                    "samples": est.samples}))
        except OSError:
            pass  # read-only scene folder: work without the cache
        return est
