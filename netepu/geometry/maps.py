r"""Full silhouette / depth / NNOPCS maps from the point renderer, evaluating few pixels.

The renderer answers arbitrary query pixels, so a full map costs one network
evaluation per pixel unless pixels are skipped. Three strategies
(:func:`render_maps`, ``mode``):

``dense``
    every pixel (NePu's way).
``culled``
    only pixels of the *candidate region* (:func:`candidate_region`): the convex
    hull of the projected keypoints dilated by ``margin`` body radii. Outside it
    the body cannot be (the margin covers the flesh around the keypoints; the
    benchmark reports how much of the true silhouette it covers).
``coarse_to_fine``
    the candidate region on a grid of stride ``2**levels`` pixels first, then
    each grid cell is either *filled* by bilinear interpolation of its four
    corners or *refined* at half the stride. A cell is refined when its corners
    disagree on the silhouette, when a corner's silhouette logit is within
    ``logit_band`` of 0 (a boundary is near), or, inside the body, when the
    corners' NNOPCS differ by more than ``nnopcs_step`` or their normalised
    depths by more than ``depth_step`` (an occlusion edge or a fold). Pixels
    are thus evaluated along boundaries and edges, and interiors are
    interpolated between grid points.

Outputs are maps of the raw head outputs; pixels never evaluated hold the
background (logit ``BACKGROUND_LOGIT``, zero depth and NNOPCS).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from netepu.geometry.renderer import RenderContext
from nsd.core.config import ConfigSection

__all__ = ["BACKGROUND_LOGIT", "MapSettings", "RenderedMaps", "candidate_region", "render_maps"]

BACKGROUND_LOGIT = -20.0  # silhouette logit written where nothing was evaluated
_HULL_DIRECTIONS = 16  # directions of the disc used to dilate the keypoint hull


@dataclass
class MapSettings(ConfigSection):
    """How :func:`render_maps` chooses the pixels it evaluates (every field is a config value).

    Attributes:
        mode: ``"dense"``, ``"culled"`` or ``"coarse_to_fine"``.
        margin: dilation of the keypoint hull, in body radii.
        levels: coarse grid stride ``2**levels`` pixels (coarse_to_fine).
        logit_band: refine cells with a corner logit within this band of 0.
        nnopcs_step: refine foreground cells whose NNOPCS corners differ by more.
        depth_step: refine foreground cells whose normalised depths differ by more.
        chunk: maximum query pixels per network call and image.
    """

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml, section `netepu.render`
    KEY: ClassVar[str] = "netepu.render"

    mode: str
    margin: float
    levels: int
    logit_band: float
    nnopcs_step: float
    depth_step: float
    chunk: int

    MODES = ("dense", "culled", "coarse_to_fine")

    def validate(self) -> None:
        if self.mode not in self.MODES:
            raise ValueError(f"render mode must be one of {self.MODES}, got {self.mode!r}")
        if self.levels < 0 or self.margin < 0 or self.chunk < 1:
            raise ValueError("levels and margin must be >= 0 and chunk >= 1")


@dataclass
class RenderedMaps:
    """Maps of one batch of views.

    Attributes:
        logit: silhouette logit, (B, H, W).
        depth: camera depth Z, (B, H, W) (0 outside the silhouette).
        depth_norm: normalised depth :math:`\\hat d`, (B, H, W).
        nnopcs: NNOPCS clamped to [0, 1], (B, H, W, 3).
        evaluated: network evaluations per image, (B,) int64.
    """

    logit: Tensor
    depth: Tensor
    depth_norm: Tensor
    nnopcs: Tensor
    evaluated: Tensor

    @property
    def silhouette(self) -> Tensor:
        """Binary silhouette, (B, H, W) bool."""
        return self.logit > 0


def candidate_region(
    uv: np.ndarray | Tensor, scale: float, margin: float, size: tuple[int, int]
) -> np.ndarray:
    """Pixels within ``margin`` body radii of the convex hull of the projected keypoints.

    Args:
        uv: projected keypoints of one view, (K, 2) pixels.
        scale: pixels per body radius (:attr:`netepu.geometry.renderer.ViewFrame.scale`).
        margin: dilation in body radii.
        size: image ``(width, height)``.

    Returns:
        bool mask, (H, W).
    """
    uv = np.asarray(torch.as_tensor(uv).detach().cpu(), dtype=np.float64)
    w, h = size
    angles = np.linspace(0, 2 * np.pi, _HULL_DIRECTIONS, endpoint=False)
    disc = margin * float(scale) * np.stack([np.cos(angles), np.sin(angles)], -1)
    pts = (uv[:, None, :] + disc[None]).reshape(-1, 2)
    pts = np.clip(pts, -4 * (w + h), 4 * (w + h))  # keep cv2's fixed-point maths in range
    hull = cv2.convexHull(np.round(pts * 16).astype(np.int32))
    out = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=4)
    return out.astype(bool)


def _query_sets(
    model_query, ctx: RenderContext, points: list[Tensor], chunk: int, dtype: torch.dtype
) -> list[Tensor]:
    """Evaluate a (possibly different) list of pixels per image; returns (n_b, 5) per image.

    Images are padded to the longest list, in chunks of ``chunk`` pixels.
    """
    B = len(points)
    counts = [p.shape[0] for p in points]
    n = max(counts) if counts else 0
    outs: list[list[Tensor]] = [[] for _ in range(B)]
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        batch = torch.zeros(B, stop - start, 2, dtype=dtype)
        for b, p in enumerate(points):
            part = p[start:stop]
            batch[b, : part.shape[0]] = part
        res = model_query(ctx, batch)
        vec = torch.cat([res["logit"][..., None], res["depth_norm"][..., None], res["nnopcs"]], -1)
        for b in range(B):
            outs[b].append(vec[b, : max(0, min(stop, counts[b]) - start)])
    return [torch.cat(o, 0) if o else torch.zeros(0, 5, dtype=dtype) for o in outs]


def _background(B: int, h: int, w: int, dtype: torch.dtype) -> Tensor:
    out = torch.zeros(B, 5, h, w, dtype=dtype)
    out[:, 0] = BACKGROUND_LOGIT
    return out


def _refine_cells(v: Tensor, s: MapSettings) -> Tensor:
    """Cells (B, h-1, w-1) of a level map v (B, 5, h, w) that need refinement."""
    def corners(x: Tensor) -> Tensor:
        return torch.stack([x[..., :-1, :-1], x[..., 1:, :-1], x[..., :-1, 1:], x[..., 1:, 1:]])

    logit = corners(v[:, 0])  # (4, B, h-1, w-1)
    fg = logit > 0
    mixed = fg.any(0) & ~fg.all(0)
    near = (logit.abs() < s.logit_band).any(0)
    inside = fg.all(0)
    c = corners(v[:, 1:])  # (4, B, 4, h-1, w-1)
    spread = c.amax(0) - c.amin(0)
    edge = (spread[:, 0] > s.depth_step) | (spread[:, 1:].amax(1) > s.nnopcs_step)
    return mixed | near | (inside & edge)


@torch.no_grad()
def render_maps(
    model_query,
    ctx: RenderContext,
    size: tuple[int, int],
    settings: MapSettings | None = None,
) -> RenderedMaps:
    """Render full maps of every view in ``ctx``.

    Args:
        model_query: ``query(ctx, uv) -> dict`` (e.g. :meth:`NeuralRenderer2D.query`).
        ctx: per-view render context (batch B).
        size: image ``(width, height)``.
        settings: pixel selection (default :class:`MapSettings`).

    Returns:
        :class:`RenderedMaps`.
    """
    s = settings or MapSettings.defaults()
    s.validate()
    w, h = size
    frame = ctx.frame
    dtype = frame.positions.dtype
    B = frame.positions.shape[0]

    if s.mode == "dense" or s.mode == "culled":
        ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        grid = torch.stack([xs, ys], -1).reshape(-1, 2).to(dtype)
        if s.mode == "dense":
            keep = [torch.ones(h * w, dtype=torch.bool) for _ in range(B)]
        else:
            keep = [torch.from_numpy(candidate_region(frame.uv[b], frame.scale[b], s.margin,
                                                      size)).reshape(-1) for b in range(B)]
        vals = _query_sets(model_query, ctx, [grid[k] for k in keep], s.chunk, dtype)
        out = _background(B, h, w, dtype).reshape(B, 5, -1)
        for b in range(B):
            out[b][:, keep[b]] = vals[b].T
        return _finish(out.reshape(B, 5, h, w), frame, torch.tensor([k.sum() for k in keep]))

    stride = 2**s.levels
    ny, nx = -(-(h - 1) // stride) + 1, -(-(w - 1) // stride) + 1
    fy, fx = (ny - 1) * stride + 1, (nx - 1) * stride + 1  # finest grid (covers the image)
    region = np.zeros((B, fy, fx), bool)
    for b in range(B):
        region[b, :h, :w] = candidate_region(frame.uv[b], frame.scale[b], s.margin, size)
    todo = _coarse_points(torch.from_numpy(region), stride)
    v = _background(B, ny, nx, dtype)
    count = torch.zeros(B, dtype=torch.int64)
    v, count = _evaluate(model_query, ctx, v, todo, stride, s.chunk, count)
    while stride > 1:
        cells = _refine_cells(v, s)
        stride //= 2
        hy, hx = 2 * v.shape[-2] - 1, 2 * v.shape[-1] - 1
        v = F.interpolate(v, size=(hy, hx), mode="bilinear", align_corners=True)
        centres = torch.zeros(B, 1, hy, hx)
        centres[:, 0, 1::2, 1::2] = cells.float()
        todo = F.max_pool2d(centres, 3, 1, 1)[:, 0] > 0
        todo[:, ::2, ::2] = False  # corners were evaluated at the coarser level
        v, count = _evaluate(model_query, ctx, v, todo, stride, s.chunk, count)
    return _finish(v[..., :h, :w], frame, count)


def _coarse_points(region: Tensor, stride: int) -> Tensor:
    """Grid points (every ``stride``-th pixel) whose four cells the region reaches into.

    Args:
        region: (B, fy, fx) bool with ``fy - 1`` and ``fx - 1`` multiples of ``stride``.

    Returns:
        (B, (fy - 1) / stride + 1, (fx - 1) / stride + 1) bool. The pooling window of a
        grid point covers its four cells, and it is evaluated at the grid points only.
    """
    return F.max_pool2d(region.float()[:, None], 2 * stride + 1, stride, stride)[:, 0] > 0


def _evaluate(model_query, ctx, v: Tensor, todo: Tensor, stride: int, chunk: int,
              count: Tensor) -> tuple[Tensor, Tensor]:
    """Evaluate the grid points ``todo`` (B, h, w) of level map ``v`` (B, 5, h, w)."""
    idx = [torch.nonzero(t) for t in todo]  # (n_b, 2) rows (y, x)
    pts = [torch.flip(i, [-1]).to(v.dtype) * stride for i in idx]
    vals = _query_sets(model_query, ctx, pts, chunk, v.dtype)
    for b, (i, val) in enumerate(zip(idx, vals, strict=True)):
        v[b, :, i[:, 0], i[:, 1]] = val.T
        count[b] += i.shape[0]
    return v, count


def _finish(v: Tensor, frame, count: Tensor) -> RenderedMaps:
    logit, depth_norm, nnopcs = v[:, 0], v[:, 1], v[:, 2:].permute(0, 2, 3, 1)
    depth = frame.depth_ref[:, None, None] + frame.radius * depth_norm
    depth = torch.where(logit > 0, depth, torch.zeros_like(depth))
    return RenderedMaps(logit, depth, depth_norm, nnopcs.clamp(0, 1), count)
