"""A user's few labelled frames from the pose tools: 2D keypoints (SLEAP, DeepLabCut) and 3D
keypoints (anipose), for evaluation on real footage and for the pose regressor.

2D labels
    * SLEAP ``.slp`` (and NWB written by SLEAP or sleap-io), read by sleap-io. A labelled
      frame's camera is the scene camera named like its video: the file's stem or the
      image folder's name (``cam0.mp4``, ``cam0/000012.png``). User instances are taken
      when a frame has any, else its predictions. An instance's individual is its track's
      name (``mouse1``): the same name in several cameras is one individual, which is what
      the cross-view score checks; untracked instances count for the mask score only.
    * DeepLabCut ``CollectedData_<scorer>.csv`` (single- or multi-animal,
      one- or three-column index), read by pandas: the camera is the video folder of the
      image path (``labeled-data/<camera>/img0123.png``), the frame the last number of the
      image name; multi-animal ``individuals`` are the individuals.
3D labels
    * anipose ``pose-3d/*.csv``: columns ``<bodypart>_x, _y, _z`` (plus ``_error``,
      ``_ncams``, ``_score``) and ``fnum`` (the frame; the row number when absent), one
      individual, in the calibration's unit (converted with ``units``).
    * 2D labels of one individual (a track name) in two or more cameras of a frame,
      triangulated with the calibration (:func:`triangulate_labels`): a keypoint labelled
      in fewer than two cameras leaves the pose out.

Missing keypoints are NaN.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import sleap_io as sio

from nsd.cameras.calibration import CameraRig
from nsd.cameras.units import UNITS
from nsd.core.errors import ConfigError
from nsd.cues.triangulation import nearest_point_to_rays

__all__ = ["Keypoints3DLabels", "Labels2D", "read_labels_2d", "read_labels_3d",
           "read_pose_labels", "triangulate_labels"]


@dataclass
class Labels2D:
    """Labelled 2D keypoints.

    Attributes:
        bodyparts: the K keypoint names.
        points: ``(camera, frame)`` -> individual -> (K, 2) pixels (OpenCV: the top-left
            pixel's centre at (0, 0)), NaN where not labelled.
        tracked: whether individuals are named across cameras (a cross-view identity).
        source: the file.
    """

    bodyparts: list[str]
    points: dict[tuple[str, int], dict[str, np.ndarray]] = field(default_factory=dict)
    tracked: bool = True
    source: str = ""

    @property
    def instances(self) -> int:
        return sum(len(v) for v in self.points.values())


def _frame_number(name: str) -> int:
    numbers = re.findall(r"\d+", Path(name).stem)
    if not numbers:
        raise ConfigError(f"labels: image {name!r} has no frame number in its name")
    return int(numbers[-1])


def _camera(candidates: list[str], cameras: list[str], what: str, source: Path) -> str:
    for c in candidates:
        if c in cameras:
            return c
    raise ConfigError(f"labels {source}: {what} names none of the scene's cameras {cameras} "
                      f"(looked for {candidates})")


def _read_sleap(path: Path, cameras: list[str]) -> Labels2D:
    labels = sio.load_file(str(path))
    if not labels.skeletons:
        raise ConfigError(f"labels {path}: no skeleton")
    skeleton = labels.skeletons[0]
    out = Labels2D([n.name for n in skeleton.nodes], source=str(path))
    tracked = True
    for lf in labels.labeled_frames:
        name = lf.video.filename
        first = Path(name[0] if isinstance(name, list) else name)
        cam = _camera([first.stem, first.parent.name], cameras, f"video {first}", path)
        insts = lf.user_instances or lf.instances
        frame = out.points.setdefault((cam, int(lf.frame_idx)), {})
        for j, inst in enumerate(insts):
            if inst.skeleton is not skeleton and [n.name for n in inst.skeleton.nodes] \
                    != out.bodyparts:
                continue
            who = inst.track.name if inst.track is not None else f"instance{j}"
            tracked &= inst.track is not None
            frame[who] = np.asarray(inst.numpy(), np.float64)[:, :2]
    out.tracked = tracked
    return out


def _read_dlc(path: Path, cameras: list[str]) -> Labels2D:
    first = path.read_text().splitlines()
    cells = first[0].split(",")
    n_index = 1 + next((i for i, c in enumerate(cells[1:]) if c.strip()), 0)
    n_header = 4 if len(first) > 1 and first[1].split(",")[0] == "individuals" else 3
    df = pd.read_csv(path, header=list(range(n_header)), index_col=list(range(n_index)))
    levels = list(df.columns.names)
    multi = "individuals" in levels
    bodyparts = list(dict.fromkeys(df.columns.get_level_values("bodyparts")))
    out = Labels2D(bodyparts, source=str(path), tracked=multi)
    for index, row in df.iterrows():
        parts = [str(p) for p in (index if isinstance(index, tuple) else (index,))]
        image = Path(*parts) if len(parts) > 1 else Path(parts[0])
        cam = _camera([image.parent.name, path.parent.name], cameras, f"image {image}", path)
        frame = out.points.setdefault((cam, _frame_number(image.name)), {})
        individuals = list(dict.fromkeys(df.columns.get_level_values("individuals"))) \
            if multi else ["individual"]
        for who in individuals:
            pts = np.full((len(bodyparts), 2), np.nan)
            for k, bp in enumerate(bodyparts):
                for j, coord in enumerate(("x", "y")):
                    key = [c for c in df.columns if c[levels.index("bodyparts")] == bp
                           and c[levels.index("coords")] == coord
                           and (not multi or c[levels.index("individuals")] == who)]
                    if key:
                        pts[k, j] = float(row[key[0]])
            if np.isfinite(pts).any():
                frame[who] = pts
    return out


def read_labels_2d(path: str | os.PathLike, cameras: list[str]) -> Labels2D:
    """Read labelled 2D keypoints (module docstring) for a scene with these cameras.

    Raises:
        ConfigError: a missing or unreadable file, or a video that names no scene camera.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"labels: {path} does not exist")
    try:
        if path.suffix.lower() in (".slp", ".nwb"):
            return _read_sleap(path, cameras)
        if path.suffix.lower() == ".csv":
            return _read_dlc(path, cameras)
    except ConfigError:
        raise
    except Exception as e:  # any reader failure names the file
        raise ConfigError(f"labels {path}: cannot be read ({type(e).__name__}: {e})") from None
    raise ConfigError(f"labels {path}: unknown format (.slp, .nwb, DeepLabCut .csv; for a "
                      "DeepLabCut .h5 give the CollectedData .csv DeepLabCut writes beside it)")


@dataclass
class Keypoints3DLabels:
    """Labelled 3D keypoints, the interface the pose regressor reads from ground truth.

    Attributes:
        bodyparts: K names.
        poses: frame -> (K, 3) world keypoints in metres (one individual).
    """

    bodyparts: list[str]
    poses: dict[int, np.ndarray | dict[int, np.ndarray]]
    source: str = ""

    @property
    def frames(self) -> np.ndarray:
        return np.array(sorted(self.poses), np.int64)

    @property
    def num_keypoints(self) -> int:
        return len(self.bodyparts)

    def keypoints3d(self, frame: int) -> dict[int, np.ndarray]:
        """Individual -> (K, 3) at ``frame`` (empty when the frame is not labelled)."""
        pose = self.poses.get(int(frame))
        if pose is None:
            return {}
        return dict(pose) if isinstance(pose, dict) else {0: pose}


def read_labels_3d(path: str | os.PathLike, units: str = "m") -> Keypoints3DLabels:
    """Read an anipose ``pose-3d`` CSV; rows with any missing keypoint are left out.

    Args:
        units: the file's length unit (``m``, ``cm``, ``mm``; anipose writes the
            calibration's, millimetres with a mm board).

    Raises:
        ConfigError: a missing file, no ``<bodypart>_x/_y/_z`` columns, an unknown unit.
    """
    path = Path(path)
    if units not in UNITS:
        raise ConfigError(f"labels units {units!r}: one of {list(UNITS)}")
    if not path.is_file():
        raise ConfigError(f"labels: {path} does not exist")
    try:
        df = pd.read_csv(path)
    except Exception as e:
        raise ConfigError(f"labels {path}: cannot be read ({type(e).__name__}: {e})") from None
    bodyparts = [c[:-2] for c in df.columns if c.endswith("_x")
                 and f"{c[:-2]}_y" in df.columns and f"{c[:-2]}_z" in df.columns]
    if not bodyparts:
        raise ConfigError(f"labels {path}: no <bodypart>_x, _y, _z columns (anipose pose-3d)")
    xyz = np.stack([df[[f"{b}_x", f"{b}_y", f"{b}_z"]].to_numpy(np.float64) for b in bodyparts],
                   axis=1) * UNITS[units]  # (rows, K, 3)
    frames = df["fnum"].to_numpy(np.int64) if "fnum" in df.columns else np.arange(len(df))
    poses = {int(f): p for f, p in zip(frames, xyz, strict=True) if np.isfinite(p).all()}
    return Keypoints3DLabels(bodyparts, poses, str(path))


def triangulate_labels(labels: Labels2D, rig: CameraRig) -> Keypoints3DLabels:
    """3D poses from 2D labels: every individual (track name) labelled in two or more
    cameras of a frame, each keypoint the point nearest to its rays
    (:func:`nsd.cues.triangulation.nearest_point_to_rays`, lens distortion undone).

    Raises:
        ConfigError: untracked labels (no individual named across cameras).
    """
    if not labels.tracked:
        raise ConfigError(f"labels {labels.source}: 2D labels need individuals named across "
                          "cameras (tracks) to be triangulated")
    views: dict[tuple[int, str], list[tuple[str, np.ndarray]]] = {}
    for (cam, frame), who in labels.points.items():
        for name, xy in who.items():
            views.setdefault((frame, name), []).append((cam, xy))
    names = sorted({n for _, n in views})
    poses: dict[int, dict[int, np.ndarray]] = {}
    for (frame, name), seen in views.items():
        pose = np.full((len(labels.bodyparts), 3), np.nan)
        for k in range(len(labels.bodyparts)):
            rays = [(rig[c].center, rig[c].unproject(xy[k][None])[0]) for c, xy in seen
                    if np.isfinite(xy[k]).all()]
            if len(rays) >= 2:
                try:
                    pose[k] = nearest_point_to_rays(*map(np.stack, zip(*rays, strict=True)))
                except ValueError:  # parallel rays
                    pass
        if np.isfinite(pose).all():
            poses.setdefault(frame, {})[names.index(name)] = pose
    return Keypoints3DLabels(labels.bodyparts, poses, labels.source)


def read_pose_labels(path: str | os.PathLike, rig: CameraRig, units: str = "m"
                     ) -> Keypoints3DLabels:
    """3D labels for the pose regressor from any labels file: an anipose ``pose-3d`` CSV
    (``units``: its length unit), or 2D labels (SLEAP, DeepLabCut) triangulated with
    ``rig`` (metres)."""
    path = Path(path)
    if path.suffix.lower() == ".csv" and path.is_file():
        head = path.read_text().split("\n", 1)[0].split(",")
        if any(c.endswith("_x") for c in head) and head[0] != "scorer":
            return read_labels_3d(path, units)
    return triangulate_labels(read_labels_2d(path, rig.names), rig)
