"""Render evaluation views with a geometry model, measure them, and draw comparison grids.

Metrics per view set (see :mod:`nsd.evaluation.maps`): silhouette IoU, NNOPCS MSE
and depth MAE (millimetres, scene units are metres) over pixels that are
foreground in both ground truth and render, the share of ground-truth pixels
inside the renderer's candidate region (``coverage``; below 1 the culling
margin is too small), and network evaluations per pixel. Depth errors are also quoted as a
share of the body size (:func:`body_length`, NeTePu's "0.81 % of a 2.2 m cow").
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from netepu.geometry.data import ViewSet
from netepu.geometry.maps import MapSettings, RenderedMaps, candidate_region, render_maps
from netepu.geometry.model import GeometryModel
from netepu.geometry.renderer import view_frame
from nsd.evaluation.maps import depth_mae, nnopcs_mse, silhouette_iou

__all__ = ["body_length", "comparison_grid", "evaluate_views", "render_view_set"]


def body_length(keypoints: torch.Tensor, species: str) -> float:
    """Body size in scene units (metres): the mean over poses (B, K, 3) of the largest
    horizontal distance between two keypoints (nose to tail of the cow, NeTePu's "2.2 m
    cow"); for bipeds the vertical extent (height)."""
    if species == "biped":
        z = keypoints[..., 2]
        return float((z.amax(1) - z.amin(1)).mean())
    xy = keypoints[..., :2]
    d = (xy[:, :, None] - xy[:, None]).norm(dim=-1)
    return float(d.flatten(1).max(1).values.mean())


@torch.no_grad()
def render_view_set(
    model: GeometryModel, views: ViewSet, settings: MapSettings, batch: int = 8
) -> RenderedMaps:
    """Render every view of ``views`` from its ground-truth keypoints (B views per call)."""
    parts = []
    for s in range(0, len(views), batch):
        sub = views.subset(list(range(s, min(len(views), s + batch))))
        code = model.encode(sub.keypoints)
        ctx = model.prepare(code, sub.camera, keypoints=sub.keypoints)
        parts.append(render_maps(model.query, ctx, views.size, settings))
    return RenderedMaps(*(torch.cat([getattr(p, f) for p in parts]) for f in
                          ("logit", "depth", "depth_norm", "nnopcs", "evaluated")))


def evaluate_views(
    model: GeometryModel, views: ViewSet, settings: MapSettings, prefix: str = ""
) -> dict[str, float]:
    """Metrics of ``model`` on ``views`` (keys prefixed with ``prefix``)."""
    was_training = model.training
    model.eval()
    maps = render_view_set(model, views, settings)
    model.train(was_training)
    pred, gt = maps.silhouette, views.mask
    both = pred & gt
    iou = silhouette_iou(pred, gt)
    frame = view_frame(views.keypoints.double(),
                       views.camera.to(torch.float64), model.radius)
    region = torch.stack([torch.from_numpy(candidate_region(
        frame.uv[i], float(frame.scale[i]), settings.margin, views.size))
        for i in range(len(views))])
    w, h = views.size
    out = {
        "iou": float(iou.mean()),
        "iou_min": float(iou.min()),
        "nnopcs_mse": float(nnopcs_mse(maps.nnopcs, views.nnopcs.float(), both)),
        "depth_mae_mm": 1000.0 * float(depth_mae(maps.depth, views.depth, both)),
        "coverage": float((region & gt).sum() / gt.sum().clamp(min=1)),
        "evaluations_per_pixel": float(maps.evaluated.double().mean() / (w * h)),
    }
    return {f"{prefix}{k}": v for k, v in out.items()}


def _colour_depth(depth: np.ndarray, mask: np.ndarray, lo: float, hi: float) -> np.ndarray:
    d = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    img = cv2.applyColorMap((255 * (1 - d)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1]
    return np.where(mask[..., None], img, 0).astype(np.uint8)


def comparison_grid(maps: RenderedMaps, views: ViewSet, n: int = 4) -> np.ndarray:
    """Rows of views; columns: silhouette, NNOPCS and depth, ground truth then render.

    Returns:
        uint8 (rows * H, 6 * W, 3) RGB.
    """
    rows = []
    for i in range(min(n, len(views))):
        gm, pm = views.mask[i].numpy(), maps.silhouette[i].numpy()
        gd, pd = views.depth[i].numpy(), maps.depth[i].numpy()
        lo, hi = (float(gd[gm].min()), float(gd[gm].max())) if gm.any() else (0.0, 1.0)
        cells = [
            np.repeat(gm[..., None], 3, -1) * 255,
            np.repeat(pm[..., None], 3, -1) * 255,
            views.nnopcs[i].float().numpy() * 255 * gm[..., None],
            maps.nnopcs[i].numpy() * 255 * pm[..., None],
            _colour_depth(gd, gm, lo, hi),
            _colour_depth(pd, pm, lo, hi),
        ]
        rows.append(np.concatenate([c.astype(np.uint8) for c in cells], 1))
    return np.concatenate(rows, 0)
