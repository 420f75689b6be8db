"""3D keypoints of exported subjects from NSD's pose regressor (where a few 3D labels exist).

The pose regressor P (stage 3, :mod:`nsd.training.pose_task`) maps a window's latent
cloud to the individual's root-relative keypoints in that window's camera
frame. For each selected frame of an ``nsd-export`` folder, every row of a
subject (one cross-view ``subject_id``; one row per camera) gets its window's
latent from the frozen decomposition of the pose checkpoint (the row's
``slot``), and P's prediction :math:`x^{cam}_v` is turned to the world frame,
:math:`x_v = R_v^\\top x^{cam}_v`. The subject's pose is the mean over its
views, placed so that its keypoint centroid lies at the point nearest to the
rays through its rows' box centres (:func:`nsd.cues.triangulation.nearest_point_to_rays`):

.. math::
    X = c + \\bar x - \\operatorname{mean}_k \\bar x_k, \\qquad \\bar x = \\frac{1}{V}\\sum_v x_v.

Subjects seen in fewer than ``min_views`` cameras are skipped (one ray fixes no
point). The output is ``keypoints3d.npz`` (:mod:`nsd.io.keypoints`), where
``subject_loss`` is the views' disagreement, the mean distance of the
:math:`x_v` to :math:`\\bar x` in scene units.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from nsd.cameras.calibration_io import read_calibration
from nsd.core.errors import CheckpointError, ConfigError
from nsd.core.trainer import load_checkpoint
from nsd.cues.triangulation import nearest_point_to_rays
from nsd.export.config import load_export_config
from nsd.inference.multiview import InferenceSettings, decompose_views, model_scene_track
from nsd.io.keypoints import SubjectKeypoints, subject_groups
from nsd.io.scene_data import SceneData
from nsd.model.build import build_model
from nsd.model.pose_regressor import PoseRegressor
from nsd.training.pose_task import ROOT

__all__ = ["load_pose_checkpoint", "regress_export", "world_keypoints"]

log = logging.getLogger(__name__)


def load_pose_checkpoint(path: str | os.PathLike) -> tuple[Any, Any, dict[str, Any]]:
    """``(decomposition model, pose regressor, config)`` of an ``nsd-train stage=pose``
    checkpoint, both in eval mode."""

    state = load_checkpoint(path)
    cfg = state.get("config") or {}
    if cfg.get("stage") != "pose" or "pose" not in state.get("modules", {}):
        raise CheckpointError(f"{path} is not a pose-regressor checkpoint (nsd-train stage=pose)")

    c = OmegaConf.create(cfg)
    model = build_model(c.model)
    model.load_state_dict(state["modules"]["model"])
    weights = state["modules"]["pose"]
    last = max((k for k in weights if k.endswith(".weight")), key=lambda k: int(k.split(".")[1]))
    keypoints = weights[last].shape[0] // 3  # the output layer: K x 3
    pose = PoseRegressor(model.encoder.points, keypoints, int(c.pose.hidden), float(c.pose.dropout))
    pose.load_state_dict(weights)
    return model.eval(), pose.eval(), cfg


def world_keypoints(
    relative: np.ndarray, rotations: np.ndarray, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, float]:
    """One subject's world keypoints from its views (the module docstring's formula).

    Args:
        relative: (V, K, 3) root-relative keypoints in each view's camera frame.
        rotations: (V, 3, 3) world-to-camera rotations R_v.
        origins, directions: (V, 3) rays through the subject's box centres.

    Returns:
        ``(keypoints (K, 3), disagreement)``: the mean distance of the views' world poses
        to their mean.
    """
    world = np.einsum("vkc,vcd->vkd", np.asarray(relative, np.float64), rotations)  # R^T x
    mean = world.mean(0)
    centre = nearest_point_to_rays(origins, directions)
    return centre + mean - mean.mean(0), float(np.linalg.norm(world - mean, axis=-1).mean())


@torch.no_grad()
def regress_export(
    export: str | os.PathLike,
    scene: str | os.PathLike,
    checkpoint: str | os.PathLike,
    out: str | os.PathLike,
    frame_step: int = 10,
    min_views: int = 2,
) -> dict[str, Any]:
    """Regress every subject of every ``frame_step``-th exported frame; writes
    ``keypoints3d.npz`` (see the module docstring).

    Args:
        export: an ``nsd-export`` folder of the same decomposition.
        scene: its scene folder.
        checkpoint: an ``nsd-train stage=pose`` checkpoint.
        out: folder for ``keypoints3d.npz``.
        frame_step: every this many exported frames.
        min_views: subjects in fewer cameras are skipped.

    Returns:
        counts and the mean disagreement between views.
    """

    if frame_step < 1 or min_views < 2:
        raise ConfigError(f"frame_step >= 1 and min_views >= 2, got {frame_step}, {min_views}")
    model, pose, cfg = load_pose_checkpoint(checkpoint)
    data, settings, decompose_kw = _as_exported(export, scene, cfg["data"])
    rig = data.rig  # the exported views
    grid = settings.grid(rig, data.frame_hw) if settings.multiview else None
    native = read_calibration(scene)  # the export's boxes are in native pixels
    images, groups, n_frames = subject_groups(
        export, frame_step, lambda a, im: im["camera"] in rig.names
    )
    fitted = SubjectKeypoints()
    dec, dec_frame = None, None
    # the hull's clustering carried through the decomposed frames, the mixture decided for
    # the scene as the export decided it
    frames = sorted({t for (t, _), anns in groups if len(anns) >= min_views})
    track = (model_scene_track(model, data.views, frames, grid, settings.mixture)
             if grid is not None else None)
    for (t, sid), anns in groups:  # in frame order: each frame is decomposed once
        if len(anns) < min_views:
            continue
        if dec_frame != t:
            views, bgs = data.views(t)
            dec = decompose_views(model, views, bgs, len(rig), settings, grid, track=track,
                                  **decompose_kw)
            dec_frame = t
        kp, spread = _subject_keypoints(pose, dec, anns, images, rig, native)
        fitted.add(t, sid, anns, kp, spread)
    fitted.save(Path(out) / "keypoints3d.npz", pose.keypoints)
    log.info("keypoints: %d subject-frames regressed, %d frames", len(fitted), n_frames)
    return fitted.summary(n_frames, "mean_view_disagreement")


def _as_exported(export, scene, d) -> tuple[SceneData, InferenceSettings, dict[str, Any]]:
    """The scene data, inference and decomposition settings the export was made with, so
    that an annotation's slot is the window whose latent is regressed. Exports written
    before multi-view inference record no inference: single-image, weights alone; those
    written before ``hull_contested`` gave the hull the same bonus on every pixel, and those
    written before ``colour_model`` had no colour models."""
    manifest = Path(export) / "manifest.json"
    ecfg = json.loads(manifest.read_text()).get("config", {}) if manifest.is_file() else {}
    recorded = dict(ecfg.get("inference", {"views": "single", "colour_sigma": 0.0}))
    if "hull_ownership" in recorded:
        recorded.setdefault("hull_contested", recorded["hull_ownership"])
    recorded.setdefault("colour_model", 0.0)  # exports from before the colour models
    settings = InferenceSettings.from_config(recorded)
    cams = ecfg.get("cameras") or d.get("cameras")
    data = SceneData(scene, d["image_size"], cams, 0.0, d.get("max_frames", 0),
                     d.get("units", "auto"), background=d.get("background", "median"))
    shipped = load_export_config()  # what an export that records no setting used
    decompose_kw = {
        "mask_threshold": float(ecfg.get("threshold", shipped.threshold)),
        "refine": str(ecfg.get("refine", shipped.refine)),
    }
    return data, settings, decompose_kw


def _subject_keypoints(pose, dec, anns, images, rig, native) -> tuple[np.ndarray, float]:
    """One subject's world keypoints from its views' regressed, root-relative poses."""
    rel, rot, origins, dirs = [], [], [], []
    for a in anns:
        name = images[int(a["image_id"])]["camera"]
        v, cam = rig.index(name), native[name]
        x = pose(dec.latent[v, int(a["slot"])][None])[0].double().numpy()
        rel.append(x - x[ROOT])
        rot.append(cam.R)
        bx, by, bw, bh = a["bbox"]
        origins.append(cam.center)
        dirs.append(cam.unproject(np.array([[bx + bw / 2 - 0.5, by + bh / 2 - 0.5]]))[0])
    return world_keypoints(np.stack(rel), np.stack(rot), np.stack(origins), np.stack(dirs))
