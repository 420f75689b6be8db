"""A scene folder checked before any long work (``nsd-check``, and the first step of
``nsd-run`` and ``nsd-train``).

Errors (:class:`~nsd.core.errors.NSDError`, naming the file, camera or frame) for what
cannot give a meaningful result:

* the calibration (unreadable, singular, non-finite: :mod:`nsd.cameras.calibration_io`),
  or camera positions that are implausible in metres (a calibration in millimetres);
* fewer than two cameras; a camera without footage; cameras of different frame counts;
* image folders whose frame names disagree across cameras (a dropped frame would pair
  every later frame with the wrong instant), images of another size within a camera,
  files that are not images.

Warnings (what to do included) for what runs but may mislead:

* frames that are blank or saturated (uniform: phantom subjects otherwise);
* footage in which nothing moves (the median background is every frame: no subject);
* footage too short for a median background (fewer than 20 frames, no plates: subjects
  that do not move away are part of it);
* a camera whose background is uncertain on more than 0.5 % of its pixels (two stable
  colours over the recording, or no colour in most frames: something stayed in place for
  part of it, or moved there most of the time; :mod:`nsd.cues.background`), with the
  share, what was done, and the advice to give a plate;
* footage folders that the calibration does not name (ignored).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import read_calibration
from nsd.cameras.units import camera_spacing
from nsd.core.errors import CalibrationError, FootageError, SceneError
from nsd.core.processes import BatchPool, resolve_workers
from nsd.cues.background import BackgroundEstimate
from nsd.io.footage import MultiViewFootage
from nsd.io.frame_sources import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    FrameSource,
    ImageFolderSource,
)

__all__ = ["MAX_CAMERA_SPACING", "SceneCheck", "check_scene", "lingered", "scene_fingerprint"]

log = logging.getLogger(__name__)

MAX_CAMERA_SPACING = 100.0  # metres: median distance between cameras above this is not metres
SAMPLE_FRAMES = 60  # frames per camera decoded for the content checks
UNIFORM_STD = 2.0  # grey levels: a frame this flat is blank, saturated or a lens cap
MOTION_LEVEL = 12.0  # grey levels from the median that count as a change
MOTION_SHARE = 1e-3  # share of pixels that must change in some frame for footage to "move"
MIN_MEDIAN_FRAMES = 20  # shorter footage without background plates: its median is doubtful
LINGER_SHARE = 0.005  # a background where something stayed on more of it is warned about
RESERVED = {"gt", "calibration", "background", "videos", "images", ".cache"}


@dataclass
class SceneCheck:
    """What :func:`check_scene` found.

    Attributes:
        scene: the scene folder.
        cameras: camera names (calibration order).
        frames: frames per camera.
        sizes: (width, height) per camera.
        camera_spacing: median distance between camera centres, calibration units.
        warnings: one line each, camera and frames named, what to do included.
        plates: camera -> its background plate (``background/``), which replaces the median.
        background: camera -> ``uncertain`` (share of its background with two stable
            colours) and ``replaced`` (share where the second colour was taken), cameras
            without a plate.
        estimates: camera -> its background estimate (what training compares frames with;
            :func:`nsd.io.background_report.write_background_report` draws them).
    """

    scene: Path
    cameras: list[str]
    frames: int
    sizes: dict[str, tuple[int, int]]
    camera_spacing: float
    warnings: list[str] = field(default_factory=list)
    plates: dict[str, str] = field(default_factory=dict)
    background: dict[str, dict[str, float]] = field(default_factory=dict)
    estimates: dict[str, BackgroundEstimate] = field(default_factory=dict, repr=False)

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable figures (``scene.json`` of nsd-run's scene stage)."""
        return {"cameras": self.cameras, "frames": self.frames,
                "sizes": {k: list(v) for k, v in self.sizes.items()},
                "camera_spacing": round(self.camera_spacing, 6), "warnings": self.warnings,
                "background_plates": self.plates, "background": self.background}


def _ranges(frames: list[int]) -> str:
    """``[1, 2, 3, 7]`` -> ``1-3, 7``."""
    out, start = [], None
    for i, f in enumerate(frames):
        if start is None:
            start = f
        if i + 1 == len(frames) or frames[i + 1] != f + 1:
            out.append(str(start) if start == f else f"{start}-{f}")
            start = None
    return ", ".join(out)


def _check_units(rig: CameraRig) -> float:
    """Median distance between camera centres (metres); an error when it cannot be metres."""
    spacing = camera_spacing(rig)
    if spacing > MAX_CAMERA_SPACING:
        raise CalibrationError(
            f"calibration {rig.source}: the cameras are a median {spacing:.0f} m apart, "
            "which is not a camera rig (the toolkit's distances, model.association_unit, "
            "prior_depth.unit and the visual hull's volume, are in metres); give the file's "
            "unit with units=mm or units=cm"
        )
    return spacing


def _frame_number(p: Path) -> str:
    """The last number in a file name (``cam0_000123.png`` -> ``123``), else the stem."""
    numbers = re.findall(r"\d+", p.stem)
    return str(int(numbers[-1])) if numbers else p.stem


def _check_names(sources: list[ImageFolderSource]) -> None:
    """Frame ``t`` of every image folder must name the same instant."""
    if len(sources) < 2:
        return
    ref = sources[0]
    ref_keys = [_frame_number(p) for p in ref.files]
    for src in sources[1:]:
        keys = [_frame_number(p) for p in src.files]
        for t, (a, b) in enumerate(zip(ref_keys, keys, strict=False)):
            if a != b:
                raise SceneError(
                    f"camera '{src.camera}': frame {t} is {src.files[t].name} where camera "
                    f"'{ref.camera}' has {ref.files[t].name}: the frame names disagree (a "
                    "dropped frame?), so later frames would pair different instants; make "
                    "the names match (the same number is the same instant)"
                )


def _check_sizes(src: ImageFolderSource) -> tuple[int, int]:
    """Every image of a folder has the first one's size; read from the file headers."""
    size = None
    for t, p in enumerate(src.files):
        try:
            with Image.open(p) as im:
                this = im.size
        except (UnidentifiedImageError, OSError) as e:
            raise FootageError(f"camera '{src.camera}' ({p}, frame {t}): not a readable image "
                               f"({type(e).__name__})") from None
        if size is None:
            size = this
        elif this != size:
            raise SceneError(
                f"camera '{src.camera}' ({p}, frame {t}): image is {this[0]}x{this[1]} but the "
                f"camera's first frame is {size[0]}x{size[1]}; every frame of a camera must "
                "have one size"
            )
    assert size is not None
    return size


def _unnamed_footage(scene: Path, names: list[str]) -> list[str]:
    """Footage folders or videos next to the calibration's cameras that it does not name."""
    found = []
    for folder in (scene, scene / "videos", scene / "images"):
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            stem = p.stem if p.is_file() else p.name
            if stem in names or p.name in RESERVED or p.name.startswith("."):
                continue
            if (p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS) or (
                p.is_dir() and any(q.suffix.lower() in IMAGE_EXTENSIONS for q in p.iterdir())
            ):
                found.append(str(p))
    return [f"footage {p} is not a camera of the calibration (it has {names}): ignored; add "
            "the camera to the calibration to use it" for p in found]


def _camera_content(src: FrameSource, frames: np.ndarray) -> tuple[list[str], bool]:
    """One camera's warnings about what its sampled ``frames`` show (blank or saturated
    frames, frames identical to the median) and whether nothing moves in them."""
    small, kept = [], []
    flat: dict[str, list[int]] = {"blank (dark)": [], "saturated (white)": [], "uniform": []}
    for t, img in zip(frames, src.iter_frames(frames), strict=True):
        grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        scale = 160 / max(grey.shape)
        if scale < 1:
            grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        g = grey.astype(np.float32)
        if g.std() < UNIFORM_STD:
            kind = ("blank (dark)" if g.mean() < 64 else "saturated (white)"
                    if g.mean() > 192 else "uniform")
            flat[kind].append(int(t))
        else:
            small.append(g)
            kept.append(int(t))
    warnings = [f"camera '{src.camera}': frames {_ranges(ts)} are {kind}; they would be "
                "decomposed into phantom subjects: remove them from the footage or leave "
                "them out (frames= in nsd-export)" for kind, ts in flat.items() if ts]
    still = False
    if len(small) >= 2:
        stack = np.stack(small)
        median = np.median(stack, axis=0)
        moving = (np.abs(stack - median) > MOTION_LEVEL).mean(axis=(1, 2))
        if moving.max() < MOTION_SHARE:
            still = True
        elif (empty := [t for t, m in zip(kept, moving, strict=True) if m == 0]):
            warnings.append(
                f"camera '{src.camera}': frames {_ranges(empty)} (of {len(frames)} sampled) "
                "are identical to the median background: no subject in view, or a frozen "
                "camera; nothing is exported for them")
    return warnings, still


def _content(footage: MultiViewFootage, sample: int, plates: dict[str, str],
             workers: int = 0) -> list[str]:
    """Warnings about what the frames show: blank or saturated frames, no motion, footage
    too short for a median background (cameras with a plate in ``plates`` need none). The
    cameras are read side by side by ``workers`` processes (0: one per available core):
    reading sampled frames of a video is a seek and a decode each (one pass in order for
    a video of variable frame rate, :class:`nsd.io.frame_sources.VideoSource`)."""
    n = footage.num_frames
    frames = np.unique(np.linspace(0, n - 1, min(n, sample)).round().astype(int))
    warnings, still = [], []
    procs = min(footage.num_views, resolve_workers("auto", workers, "cpu"))
    with BatchPool(lambda src: _camera_content(src, frames), procs, procs,
                   job="scene check", remedy="threads=") as pool:
        for src, (said, is_still) in pool.map(footage.sources):
            warnings += said
            if is_still:
                still.append(src.camera)
    if still and len(still) == len(footage.sources):
        warnings.append(
            f"nothing moves in any camera ({len(frames)} frames sampled): the median "
            "background is every frame, so no subject can be found; check that this is the "
            "right footage, or give a background plate (background/<camera>.png: a picture "
            "of the empty arena)")
    elif still:
        warnings.append(f"cameras {still}: nothing moves in their footage; check that they "
                        "film the subjects")
    if n < MIN_MEDIAN_FRAMES and len(plates) < footage.num_views and len(still) < footage.num_views:
        warnings.append(
            f"the footage has {n} frames: the median background of so few frames holds every "
            "subject that does not move away from its place, and such subjects will not be "
            "found; give a background plate (background/<camera>.png: a picture of the empty "
            "arena) or longer footage")
    return warnings


def lingered(est: BackgroundEstimate, method: str) -> bool:
    """Does a camera's background estimate say a subject may have been taken for background?

    With ``modes``: something stayed for a stretch and the estimate replaced it or kept a
    subject-like colour (``BackgroundEstimate.stayed``) on more than ``LINGER_SHARE`` of the
    image; the other uncertain pixels, where subjects pass in most frames or stood at the start
    or the end beside the kept floor, kept the right colour on the synthetic scenes measured
    (docs/benchmarks/background.md). With ``median`` every uncertain pixel keeps the
    median, whatever it shows: more than ``LINGER_SHARE`` uncertain.
    """
    share = est.stayed_share if method == "modes" else est.uncertain_share
    return share > LINGER_SHARE


def _background(
    footage: MultiViewFootage, plates: dict[str, str], workers: int = 0
) -> tuple[dict[str, BackgroundEstimate], dict[str, dict[str, float]], list[str]]:
    """Every camera's background estimate (a plate's median where there is one), the
    shares of the plate-less ones, and a warning per plate-less camera whose estimate says a
    subject may have been taken for background (:func:`lingered`; footage long enough for an
    estimate)."""
    estimates = dict(zip(footage.camera_names, footage.background_estimates(workers=workers),
                         strict=True))
    report, warnings = {}, []
    for cam, est in estimates.items():
        if cam in plates or footage.num_frames < MIN_MEDIAN_FRAMES:
            continue  # a plate is the background; too short footage is said by _content
        report[cam] = {"uncertain": round(est.uncertain_share, 6),
                       "stayed": round(est.stayed_share, 6),
                       "replaced": round(float(est.replaced.mean()), 6)}
        if lingered(est, footage.background_method):
            if footage.background_method == "modes":
                what = (f"on {est.stayed_share:.1%} of its background something stayed in "
                        f"place for a stretch of the recording (one colour for a stretch, "
                        f"another outside it; {est.uncertain_share:.1%} uncertain in all); "
                        f"the colour of the frames without it was taken on "
                        f"{est.replaced.mean() / est.stayed_share:.0%} of that")
            else:
                what = (f"{est.uncertain_share:.1%} of its background is uncertain (two "
                        f"stable colours over the recording, or none in most frames), and the "
                        f"median was kept there (data.background=modes replaces what stayed)")
            warnings.append(
                f"camera '{cam}': {what}. Where a subject stays, it may be missed: "
                f"give a background plate ({footage.scene / 'background' / cam}.png, the "
                f"empty arena) or footage in which it moves away")
    return estimates, report, warnings


def check_scene(scene: str | os.PathLike, cameras: list[str] | None = None,
                sample: int = SAMPLE_FRAMES, units: str = "auto",
                background: str = "median", workers: int = 0) -> SceneCheck:
    """Check a scene folder; warnings are logged and returned.

    Args:
        scene: the scene folder.
        cameras: the cameras to use (default: every camera of the calibration).
        sample: frames per camera decoded for the content checks.
        units: the calibration's length unit (:mod:`nsd.cameras.units`).
        background: the background method (``data.background``), whose estimates are
            made here (and cached for training) to report their uncertain pixels.
        workers: processes checking the cameras' frames and estimating their backgrounds
            side by side (0: one per available core; the run's ``threads`` where it sets
            them).

    Raises:
        NSDError: what cannot give a meaningful result (see the module docstring).
    """
    scene = Path(scene)
    if not scene.is_dir():
        raise FootageError(f"scene: {scene} is not a folder (give scene=<scene folder>)")
    rig = read_calibration(scene, units)
    footage = MultiViewFootage(scene, cameras, calibration=rig, background=background)
    if footage.num_views < 2:
        raise SceneError(
            f"scene {scene}: {footage.num_views} camera ({footage.camera_names}); the "
            "decomposition re-synthesises one camera from another and needs at least 2")
    spacing = _check_units(footage.rig)
    folders = [s for s in footage.sources if isinstance(s, ImageFolderSource)]
    sizes = {s.camera: _check_sizes(s) for s in folders}
    sizes.update({s.camera: tuple(s.size) for s in footage.sources if s.camera not in sizes})
    _check_names(folders)
    plates = {src.camera: str(plate.path) for v, src in enumerate(footage.sources)
              if (plate := footage.plate(v)) is not None}  # a plate of another size raises
    logged = ([rig.units_note] if rig.units_note else []) + footage.notes  # where they arose
    warnings = logged + _unnamed_footage(scene, rig.names) + _content(footage, sample, plates,
                                                                       workers)
    estimates, report, lingering = _background(footage, plates, workers)
    warnings += lingering
    for w in warnings[len(logged):]:
        log.warning("scene %s: %s", scene.name, w)
    return SceneCheck(scene, footage.camera_names, footage.num_frames, sizes, spacing,
                      warnings, plates, report, estimates)


def scene_fingerprint(scene: str | os.PathLike) -> str:
    """Changes when any file of the scene folder changes (name, size or modification time);
    caches and the ground truth excluded. A cache key: replacing a video or the calibration
    re-runs what depends on the scene."""
    scene = Path(scene)
    h = hashlib.sha256()
    for root, dirs, files in os.walk(scene):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and not (
            Path(root) == scene and d == "gt"))
        for name in sorted(files):
            p = Path(root) / name
            st = p.stat()
            h.update(f"{p.relative_to(scene)}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]
