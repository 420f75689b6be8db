"""Label-free 3D keypoints of exported subjects: inverse rendering of their multi-view masks.

For each selected frame of an ``nsd-export`` folder, the visible masks of one
subject (one cross-view ``subject_id``) in every camera that shows it go into
:func:`netepu.geometry.inverse.invert_silhouettes` with a trained NeTePu geometry model
and the scene's calibration; the recovered world keypoints are written for
every annotation (camera-frame row) of that subject in that frame, in the
``keypoints3d.npz`` format ``netepu-embed`` reads (:mod:`nsd.io.keypoints`;
``subject_loss`` is the inversion's final silhouette loss).

Visible masks of an occluded subject are partial; the inversion then fits a
body to what is visible in each view (the multi-view silhouette loss is a
per-view mean, so a view where the subject is mostly hidden weighs as much as
the others). Templates (the inversion's starting poses) are poses of the
geometry model's own synthetic individual (:func:`template_poses`), so no
training data is needed at run time.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pycocotools import mask as mask_utils

from netepu.geometry.data import DataConfig
from netepu.geometry.inverse import InverseSettings, invert_silhouettes
from netepu.geometry.maps import MapSettings
from netepu.geometry.model import load_geometry_model
from nsd.cameras.calibration_io import read_calibration
from nsd.core.errors import ConfigError
from nsd.io.keypoints import SubjectKeypoints, subject_groups
from nsd.synth import make_individual
from nsd.synth.motion import sample_pose

__all__ = ["invert_export", "template_poses"]

log = logging.getLogger(__name__)


def template_poses(data_cfg: dict[str, Any], n: int = 2, seed: int = 0) -> torch.Tensor:
    """``n`` random poses (n, K, 3) of the synthetic individual a geometry model was trained on."""

    cfg = DataConfig.from_mapping(data_cfg)
    ind = make_individual(
        cfg.species,
        identity=cfg.identity,
        seed=cfg.seed,
        proportion_variation=cfg.proportion_variation,
    )
    rng = np.random.default_rng(seed)
    return torch.stack(
        [ind.keypoints3d(sample_pose(ind, rng, cfg.pose_variation)).float() for _ in range(n)]
    )


def invert_export(
    export: str | os.PathLike,
    scene: str | os.PathLike,
    checkpoint: str | os.PathLike,
    out: str | os.PathLike,
    frame_step: int = 10,
    min_views: int = 2,
    min_area: int = 16,
    steps: int = 120,
    templates: int = 2,
    max_subject_frames: int = 0,
) -> dict[str, Any]:
    """Invert every subject of every ``frame_step``-th exported frame; writes ``keypoints3d.npz``.

    Args:
        export: an ``nsd-export`` folder.
        scene: its scene folder (for the calibration).
        checkpoint: a ``netepu-train`` geometry checkpoint.
        out: folder for ``keypoints3d.npz``.
        frame_step: invert every this many exported frames.
        min_views: subjects seen (visible area >= ``min_area`` pixels) in fewer cameras
            are skipped.
        steps: Adam steps per inversion.
        templates: starting poses (each tried at 4 headings).
        max_subject_frames: stop after this many inversions (0: no limit).

    Returns:
        counts and the mean final silhouette loss.
    """

    if frame_step < 1 or min_views < 1:
        raise ConfigError(f"frame_step and min_views must be >= 1, got {frame_step}, {min_views}")
    model, config = load_geometry_model(checkpoint)
    net = config["netepu"]
    starts = template_poses(net["data"], templates)
    render = net.get("render") or MapSettings.default_mapping()  # checkpoints before it: defaults
    settings = InverseSettings(steps=steps, margin=float(render["margin"]))
    rig = read_calibration(scene)
    cams = rig.stacked(torch.float32)
    images, groups, n_frames = subject_groups(
        export, frame_step, lambda a, im: a["area"] >= min_area
    )
    fitted = SubjectKeypoints()
    for (t, sid), anns in groups:
        anns = _views_of_one_size(anns, images)
        if len(anns) < min_views:
            continue
        if max_subject_frames and len(fitted) >= max_subject_frames:
            break
        cam_idx = [rig.index(images[a["image_id"]]["camera"]) for a in anns]
        masks = np.stack([mask_utils.decode(a["segmentation"]) for a in anns]).astype(bool)
        rng = np.random.default_rng(t)
        res = invert_silhouettes(
            model, torch.from_numpy(masks), cams[cam_idx], starts, settings, rng
        )
        fitted.add(t, sid, anns, res.keypoints.float().numpy(), res.loss)
        log.info(
            "keypoints: frame %d subject %d from %d views, loss %.3f", t, sid, len(anns), res.loss
        )
    fitted.save(Path(out) / "keypoints3d.npz", starts.shape[1])
    return fitted.summary(n_frames, "mean_loss")


def _views_of_one_size(anns: list[dict], images: dict[int, dict]) -> list[dict]:
    """The subject's views whose images share the most common size: the inversion takes
    one (V, H, W) stack of masks."""

    def size(a: dict) -> tuple[int, int]:
        im = images[a["image_id"]]
        return int(im["height"]), int(im["width"])

    sizes = [size(a) for a in anns]
    if len(set(sizes)) == 1:
        return anns
    common = max(set(sizes), key=sizes.count)
    return [a for a, s in zip(anns, sizes, strict=True) if s == common]
