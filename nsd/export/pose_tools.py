"""The export in the files the pose tools read: SLEAP, NWB, DeepLabCut, TRC and C3D.

Written with the tools' own libraries where one exists: sleap-io builds one ``Labels`` (a
video per camera, a track per identity, per camera-frame the subjects' poses, masks and
boxes, the cameras as a recording session) and writes it as SLEAP's ``.slp``, as NWB
(ndx-pose ``PoseEstimation``, through sleap-io) and as DeepLabCut's multi-animal CSV (one
per camera); ezc3d writes C3D. TRC (OpenSim, Pose2Sim) has no maintained Python writer:
it is a tab-separated text format, written here.

The pose of a subject in a camera: its 3D keypoints projected into that camera when the
pipeline fitted keypoints (:class:`KeypointFile`: a ``keypoints3d.npz`` and the skeleton it
is on, nodes named by the species or ``kp0``..), else one node, ``centroid``, the centroid
of its visible mask. 3D files hold, per identity, its world position
(:mod:`nsd.export.positions`) and, with keypoints, its keypoints, in metres.

Several skeletons (a scene of two species, one keypoint file each): the ``.slp`` file holds
every skeleton, each instance on its own; the NWB file holds every skeleton, each track's
``PoseEstimation`` linked to its own (built from sleap-io's parts, :func:`_write_nwb`);
DeepLabCut's tables take one skeleton, so they are written per skeleton; TRC and C3D name
each identity's markers by its own skeleton's nodes.

Layout (``<out>/``)::

    subjects.slp            SLEAP labels (sleap-io, SLEAP, the movement package read it)
    subjects.nwb            NWB with ndx-pose PoseEstimation per camera and track
    dlc/<camera>.csv        DeepLabCut multi-animal CSV (scorer nsd-netepu)
    dlc/<skeleton>/<camera>.csv   the same, per skeleton, when there are several
    trajectories.trc        markers id<k> (and id<k>_<node>) per frame, metres
    trajectories.c3d        the same markers, metres
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import ezc3d
import numpy as np
import sleap_io as sio
from pycocotools import mask as mask_utils
from pynwb import NWBHDF5IO, NWBFile
from sleap_io.io import nwb_predictions

from nsd.cameras.calibration import CameraRig
from nsd.core.atomic import atomic_write_text
from nsd.export.positions import mask_centroid
from nsd.io.footage import footage_frame_rate
from nsd.io.frame_sources import ImageFolderSource, find_source

__all__ = ["POSE_TOOL_FORMATS", "KeypointFile", "one_row_per_identity", "read_trc",
           "write_c3d", "write_pose_tool_files", "write_trc"]

log = logging.getLogger(__name__)

POSE_TOOL_FORMATS = ("slp", "nwb", "dlc", "trc", "c3d")
SCORER = "nsd-netepu"


@dataclass(frozen=True)
class KeypointFile:
    """Fitted 3D keypoints and the skeleton they are on.

    Attributes:
        path: a ``keypoints3d.npz``: ``id`` (R,) annotation ids, ``keypoints`` (R, K, 3)
            world keypoints, metres.
        skeleton: the skeleton's name (a species); distinct per file.
        nodes: its K node names (default ``kp0``..``kp<K-1>``).
        edges: its bones, pairs of node indices.
    """

    path: Path
    skeleton: str = "subject"
    nodes: tuple[str, ...] = ()
    edges: tuple[tuple[int, int], ...] = ()


@dataclass
class _Bodies:
    """The keypoint files read: every skeleton, and every row's skeleton and keypoints."""

    skeletons: dict[str, sio.Skeleton]
    rows: dict[int, tuple[str, np.ndarray]]  # annotation id -> (skeleton, (K, 3))


def _read_bodies(files: Sequence[KeypointFile]) -> _Bodies | None:
    """Read ``files``; ValueError naming the file for a node count that does not match its
    keypoints, a skeleton named twice, or a row fitted in two files."""
    skeletons: dict[str, sio.Skeleton] = {}
    rows: dict[int, tuple[str, np.ndarray]] = {}
    for f in files:
        with np.load(f.path) as z:
            ids, kps = z["id"].tolist(), np.asarray(z["keypoints"], np.float64)
        k = kps.shape[1] if kps.ndim == 3 else 0
        if f.nodes and len(f.nodes) != k:
            raise ValueError(f"{f.path}: {k} keypoints, but skeleton {f.skeleton!r} has "
                             f"{len(f.nodes)} nodes")
        if f.skeleton in skeletons:
            raise ValueError(f"{f.path}: skeleton {f.skeleton!r} is named by two keypoint files")
        nodes = list(f.nodes) or [f"kp{j}" for j in range(k)]
        skeletons[f.skeleton] = sio.Skeleton(nodes, edges=[list(e) for e in f.edges],
                                             name=f.skeleton)
        for aid, kp in zip(ids, kps, strict=True):
            if aid in rows:
                raise ValueError(f"{f.path}: row {aid} is also fitted on skeleton "
                                 f"{rows[aid][0]!r}")
            rows[int(aid)] = (f.skeleton, kp)
    return _Bodies(skeletons, rows) if skeletons else None


def _video(scene: Path, camera: str) -> sio.Video:
    source = find_source(scene, camera)
    if isinstance(source, ImageFolderSource):
        # an image sequence is stored with its backend's record (a list alone does not load)
        return sio.Video(filename=[str(p) for p in source.files])
    return sio.Video(filename=str(source.path), open_backend=False)


def _cameras(coco: dict, rig: CameraRig) -> list[str]:
    """The exported cameras in calibration order."""
    return sorted({im["camera"] for im in coco["images"]}, key=rig.names.index)


def _session(rig: CameraRig, videos: dict[str, sio.Video]) -> sio.RecordingSession | None:
    """The cameras as a sleap-io recording session; None when a lens does not fit its
    five-coefficient OpenCV model (fisheye, rational or thin-prism lenses)."""
    if any(c.fisheye or np.any(c.dist[5:]) for c in rig):
        log.info("pose tools: a lens model beyond k1, k2, p1, p2, k3: the .slp file holds no "
                 "recording session (the calibration file stays the reference)")
        return None
    cams = {c.name: sio.Camera(matrix=c.K, dist=np.resize(np.r_[c.dist, np.zeros(5)], 5),
                               size=c.size, rvec=cv2.Rodrigues(c.R)[0].ravel(), tvec=c.t,
                               name=c.name) for c in rig}
    session = sio.RecordingSession(camera_group=sio.CameraGroup(cameras=list(cams.values())))
    for name, video in videos.items():
        session.add_video(video, cams[name])
    return session


def one_row_per_identity(annotations: list[dict], row_ids: dict[int, int]
                         ) -> tuple[dict[int, int], int]:
    """``row_ids`` with at most one row per identity and camera-frame: where several rows of
    a camera-frame share an identity (the identities of rows between coded frames come from
    their tracks, which can meet), the row of highest score keeps it (then the larger
    area, then the lower id) and the others get -1. Returns the new map and how many rows
    lost their identity."""
    def rank(a: dict) -> tuple[float, float, int]:
        return float(a.get("score", 1.0)), float(a.get("area", 0.0)), -int(a["id"])

    best: dict[tuple[str, int, int], dict] = {}
    out = dict(row_ids)
    for a in annotations:
        ident = row_ids.get(int(a["id"]), -1)
        if ident < 0:
            continue
        key = (str(a["camera"]), int(a["frame"]), ident)
        held = best.setdefault(key, a)
        if held is a:
            continue
        keep, lose = (a, held) if rank(a) > rank(held) else (held, a)
        best[key] = keep
        out[int(lose["id"])] = -1
    return out, sum(1 for k, v in out.items() if v < 0 <= row_ids.get(k, -1))


def build_labels(coco: dict, scene: Path, rig: CameraRig, row_ids: dict[int, int],
                 bodies: _Bodies | None) -> sio.Labels:
    """One sleap-io ``Labels`` of the export (module docstring).

    Args:
        coco: ``subjects.coco.json`` of the export.
        scene: the scene folder (the videos the labels point at).
        rig: the calibration at native size, metres.
        row_ids: annotation id -> identity (a track each); rows without one are left out.
        bodies: every row's skeleton and world keypoints, or None (a centroid each).
    """
    skeletons = (bodies.skeletons if bodies
                 else {"subject": sio.Skeleton(["centroid"], name="subject")})
    cameras = _cameras(coco, rig)
    videos = {c: _video(scene, c) for c in cameras}
    tracks = {i: sio.Track(name=f"id{i}") for i in sorted(set(row_ids.values())) if i >= 0}
    frames: dict[tuple[str, int], sio.LabeledFrame] = {}
    for a in coco["annotations"]:
        aid, ident = int(a["id"]), row_ids.get(int(a["id"]), -1)
        if ident < 0:
            continue
        key = (a["camera"], int(a["frame"]))
        lf = frames.get(key)
        if lf is None:
            lf = frames[key] = sio.LabeledFrame(video=videos[key[0]], frame_idx=key[1])
        track, score = tracks[ident], float(a.get("score", 1.0))
        mask = mask_utils.decode(a["segmentation"]).astype(bool)  # decoded once per row
        if bodies and aid in bodies.rows:
            name, kp = bodies.rows[aid]
            uv, z = rig[key[0]].project(kp)
            points = np.where((z > 0)[:, None], uv, np.nan)
        elif not bodies and (centroid := mask_centroid(mask)) is not None:
            name, points = "subject", centroid[None]
        else:
            continue
        inst = sio.PredictedInstance.from_numpy(points, skeleton=skeletons[name], score=score,
                                                point_scores=np.full(len(points), score),
                                                track=track)
        lf.instances.append(inst)
        lf.masks.append(sio.PredictedSegmentationMask.from_numpy(
            mask, score=score, track=track, instance=inst))
        x, y, w, h = (float(v) for v in a["bbox"])
        lf.bboxes.append(sio.PredictedBoundingBox.from_xywh(x, y, w, h, score=score,
                                                            track=track, instance=inst))
    session = _session(rig.select(cameras), videos)
    return sio.Labels(labeled_frames=[frames[k] for k in sorted(frames) if frames[k].instances],
                      videos=list(videos.values()), skeletons=list(skeletons.values()),
                      tracks=list(tracks.values()), sessions=[session] if session else [],
                      provenance={"source": SCORER})


def _used_videos(labels: sio.Labels) -> sio.Labels:
    """``labels`` with only the videos that hold an instance: sleap-io's NWB writer fails
    (a KeyError on the video's path) on a video without one, e.g. a camera in which no
    subject got keypoints (``netepu.keypoints.frame_step``)."""
    used = {id(lf.video) for lf in labels.labeled_frames if lf.instances}
    if len(used) == len(labels.videos):
        return labels
    return sio.Labels(labeled_frames=list(labels.labeled_frames),
                      videos=[v for v in labels.videos if id(v) in used],
                      skeletons=labels.skeletons, tracks=labels.tracks,
                      provenance=labels.provenance)


def _of_skeleton(labels: sio.Labels, skeleton: sio.Skeleton) -> sio.Labels:
    """The instances of ``labels`` on ``skeleton`` alone (every video kept, in order): the
    DeepLabCut and NWB writers take one skeleton per call."""
    frames = [sio.LabeledFrame(video=lf.video, frame_idx=lf.frame_idx,
                               instances=[i for i in lf.instances if i.skeleton is skeleton])
              for lf in labels.labeled_frames]
    return sio.Labels(labeled_frames=[lf for lf in frames if lf.instances],
                      videos=labels.videos, skeletons=[skeleton], tracks=labels.tracks,
                      provenance=labels.provenance)


def _write_nwb(labels: sio.Labels, path: Path, rate: float) -> None:
    """The NWB file of ``labels`` (ndx-pose, through sleap-io), every skeleton in it,
    atomically. Timestamps in seconds for every footage frame (sleap-io's default, one per
    frame with data, misplaces exports that do not start at frame 0).

    sleap-io's writer gives each track of a video the video's first skeleton, and its
    append adds a skeleton through a method ndx-pose no longer has; so the file is built
    here from its parts: every skeleton first, then one skeleton's instances at a time."""
    last = max(lf.frame_idx for lf in labels.labeled_frames) if labels else 0
    meta = {"video_timestamps": np.arange(last + 1) / rate, "video_sample_rate": rate}
    parts = [_used_videos(_of_skeleton(labels, s)) for s in labels.skeletons]
    nwb = NWBFile(session_description="Processed SLEAP pose data", identifier=str(uuid.uuid4()),
                  session_start_time=datetime.datetime.now(datetime.UTC))
    skeletons = nwb_predictions.create_skeleton_container(labels, nwb)
    for part in parts:
        if part.labeled_frames:
            nwb_predictions.append_nwb_data(part, nwb, dict(meta), skeletons)
    tmp = path.with_name(f".{path.stem}.tmp.nwb")
    with NWBHDF5IO(str(tmp), "w") as io:
        io.write(nwb)
    os.replace(tmp, path)


def _markers(positions: dict[tuple[int, int], tuple[np.ndarray, int]],
             keypoints: dict[tuple[int, int], tuple[str, np.ndarray]],
             skeletons: dict[str, sio.Skeleton],
             ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Marker names, frames (F,) and points (F, M, 3) (NaN: not seen).

    Args:
        positions: ``(frame, id)`` -> (world position, views): markers ``id<k>``.
        keypoints: ``(frame, id)`` -> (skeleton, (K, 3) keypoints): markers
            ``id<k>_<node>``, or ``id<k>_<skeleton>_<node>`` for an identity fitted on two
            skeletons.
        skeletons: the skeletons by name (their node names).
    """
    ids = sorted({i for _, i in positions} | {i for _, i in keypoints})
    names = [f"id{i}" for i in ids]
    blocks = sorted({(i, s) for (_, i), (s, _) in keypoints.items()})  # (identity, skeleton)
    start: dict[tuple[int, str], int] = {}
    for i, s in blocks:
        start[(i, s)] = len(names)
        prefix = f"id{i}_" if sum(b[0] == i for b in blocks) == 1 else f"id{i}_{s}_"
        names += [prefix + n for n in skeletons[s].node_names]
    all_frames = sorted({f for f, _ in positions} | {f for f, _ in keypoints})
    frames = np.arange(all_frames[0], all_frames[-1] + 1) if all_frames else np.zeros(0, int)
    pts = np.full((len(frames), len(names), 3), np.nan)
    col = {i: c for c, i in enumerate(ids)}
    for (f, i), (xyz, _) in positions.items():
        pts[f - frames[0], col[i]] = xyz
    for (f, i), (s, kp) in keypoints.items():
        pts[f - frames[0], start[(i, s)]:start[(i, s)] + len(kp)] = kp
    return names, frames, pts


def write_trc(path: Path, names: list[str], frames: np.ndarray, points: np.ndarray,
              fps: float) -> None:
    """A TRC file (OpenSim / Pose2Sim), metres; NaN points are left empty; atomically.

    Args:
        names: M marker names; frames: (F,) 0-based footage frames; points: (F, M, 3).
    """
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{fps:.6g}\t{fps:.6g}\t{len(frames)}\t{len(names)}\tm\t{fps:.6g}\t"
        f"{int(frames[0]) + 1 if len(frames) else 1}\t{len(frames)}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{k}\tY{k}\tZ{k}" for k in range(1, len(names) + 1)),
        "",
    ]
    for f, row in zip(frames, points, strict=True):
        vals = ["" if not np.isfinite(v) else f"{v:.6f}" for v in row.reshape(-1)]
        lines.append(f"{int(f) + 1}\t{f / fps:.6f}\t" + "\t".join(vals))
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_trc(path: Path) -> tuple[list[str], np.ndarray, np.ndarray, float]:
    """Marker names, 0-based frames (F,), points (F, M, 3) (NaN: empty) and the rate."""
    rows = Path(path).read_text().split("\n")
    rate = float(rows[2].split("\t")[0])
    names = [n for n in rows[3].split("\t")[2:] if n]
    data = [r.split("\t") for r in rows[6:] if r.strip()]
    frames = np.array([int(r[0]) - 1 for r in data], np.int64)
    pts = np.array([[float(v) if v else np.nan for v in r[2:2 + 3 * len(names)]] for r in data])
    return names, frames, pts.reshape(len(frames), len(names), 3), rate


def write_c3d(path: Path, names: list[str], frames: np.ndarray, points: np.ndarray,
              fps: float) -> None:
    """A C3D file (ezc3d), metres; NaN points are C3D's missing points; atomically.

    Args:
        names: M marker names; frames: (F,) 0-based footage frames; points: (F, M, 3).
    """
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [float(fps)]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(names)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    data = np.ones((4, len(names), len(frames)))
    data[:3] = points.transpose(2, 1, 0)
    c3d["data"]["points"] = data
    c3d.add_parameter("TRIAL", "ACTUAL_START_FIELD", [int(frames[0]) + 1 if len(frames) else 1, 0])
    tmp = path.with_name(f".{path.stem}.tmp.c3d")  # ezc3d appends .c3d to other names
    c3d.write(str(tmp))
    os.replace(tmp, path)


def _frame_rate(scene: Path, cameras: list[str], fps: float | None) -> float:
    """The footage's frame rate: ``fps`` when given, else the footage's own
    (:func:`nsd.io.footage.footage_frame_rate`), else 30 (said)."""
    if fps:
        return float(fps)
    rate = footage_frame_rate(scene, cameras)
    if rate:
        return rate
    log.warning("pose tools: %s has no frame rate (image folders): TRC/C3D use 30 frames/s; "
                "give formats.fps", scene)
    return 30.0


def write_pose_tool_files(
    export: str | os.PathLike,
    scene: str | os.PathLike,
    rig: CameraRig,
    out: str | os.PathLike,
    row_ids: dict[int, int] | None = None,
    positions: dict[tuple[int, int], tuple[np.ndarray, int]] | None = None,
    keypoints: Sequence[KeypointFile] = (),
    formats: tuple[str, ...] = POSE_TOOL_FORMATS,
    fps: float | None = None,
) -> dict[str, Any]:
    """Write the export in the pose tools' formats (module docstring).

    Args:
        export: an ``nsd-export`` folder.
        scene: its scene folder.
        rig: the calibration at native size, in metres.
        out: the folder to write.
        row_ids: annotation id -> identity (default: the rows' ``subject_id``).
        positions: ``(frame, id)`` -> (world position, views), for TRC/C3D.
        keypoints: fitted keypoints, one :class:`KeypointFile` per skeleton (a species);
            none: a centroid per row.
        formats: which of :data:`POSE_TOOL_FORMATS`.
        fps: frame rate of the 3D files (default: the footage's).

    Returns:
        Counts per file (instances, tracks, frames, markers).
    """
    export, scene, out = Path(export), Path(scene), Path(out)
    unknown = sorted(set(formats) - set(POSE_TOOL_FORMATS))
    if unknown:
        raise ValueError(f"formats: unknown {unknown}; choose from {list(POSE_TOOL_FORMATS)}")
    out.mkdir(parents=True, exist_ok=True)
    coco = json.loads((export / "subjects.coco.json").read_text())
    if row_ids is None:
        row_ids = {int(a["id"]): int(a["subject_id"]) for a in coco["annotations"]}
    bodies = _read_bodies(keypoints)
    rate = _frame_rate(scene, rig.names, fps)
    summary: dict[str, Any] = {"fps": rate}
    row_ids, doubled = one_row_per_identity(coco["annotations"], row_ids)
    if doubled:
        log.warning("pose tools: %d rows share their identity with another row of their "
                    "camera-frame; the tools' files hold one instance per identity and "
                    "camera-frame, so the row of higher score is kept", doubled)
        summary["rows_left_out"] = doubled
    if not any(row_ids.get(int(a["id"]), -1) >= 0 for a in coco["annotations"]):
        log.warning("pose tools: the export holds no subject with an identity: no files written")
        summary.update(instances=0, tracks=0, files=[], skipped="no subjects")
        return summary
    if {"slp", "nwb", "dlc"} & set(formats):
        labels = build_labels(coco, scene, rig, row_ids, bodies)
        summary["instances"] = sum(len(lf.instances) for lf in labels.labeled_frames)
        summary["tracks"] = len(labels.tracks)
        if bodies:
            summary["skeletons"] = {s.name: sum(i.skeleton is s for lf in labels.labeled_frames
                                                for i in lf.instances)
                                    for s in labels.skeletons}
        if "slp" in formats:
            sio.save_slp(labels, str(out / "subjects.slp"))
        # DeepLabCut and NWB name a camera's source by one path: an image folder's
        for camera, video in zip(_cameras(coco, rig), labels.videos, strict=True):
            if isinstance(video.filename, list):
                video.replace_filename(str(find_source(scene, camera).path), open=False)
        if "dlc" in formats:  # a table takes one skeleton: one folder each when several
            several = len(labels.skeletons) > 1
            for skeleton in labels.skeletons:
                part = _of_skeleton(labels, skeleton) if several else labels
                folder = out / "dlc" / skeleton.name if several else out / "dlc"
                folder.mkdir(parents=True, exist_ok=True)
                for i, camera in enumerate(_cameras(coco, rig)):  # the labels' video order
                    # sleap-io writes no per-point likelihood to DeepLabCut tables (its DLC
                    # writer drops point scores): the table is a labelled-data table, x and y
                    sio.save_csv(part, str(folder / f"{camera}.csv"), format="dlc", video=i,
                                 scorer=SCORER, include_score=False)
        if "nwb" in formats:
            _write_nwb(labels, out / "subjects.nwb", rate)
    if {"trc", "c3d"} & set(formats):
        kp3d = {}  # one pose per identity and frame
        for a in coco["annotations"] if bodies else []:
            ident = row_ids.get(int(a["id"]), -1)
            if ident >= 0 and int(a["id"]) in bodies.rows:
                kp3d[(int(a["frame"]), ident)] = bodies.rows[int(a["id"])]
        names, frames, pts = _markers(positions or {}, kp3d,
                                      bodies.skeletons if bodies else {})
        if "trc" in formats:
            write_trc(out / "trajectories.trc", names, frames, pts, rate)
        if "c3d" in formats:
            write_c3d(out / "trajectories.c3d", names, frames, pts, rate)
        summary.update(markers=len(names), frames=len(frames))
    summary["files"] = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    return summary
