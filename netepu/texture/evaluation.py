r"""Evaluate a texture model: colour PSNR of held-out poses and cameras, codes, synthesis grids.

* **Codes** (:func:`heldout_codes`): :math:`\mu` of every held-out crop (every
  view of every held-out pose, every texture), from *predicted* NNOPCS crops.
* **Colour PSNR** (:func:`colour_psnr`): per image over the ground-truth
  foreground pixels, :math:`10 \log_{10}(1 / \mathrm{MSE})` with colours in
  [0, 1], averaged over images; renders only the foreground pixels (the
  renderer's speed discipline; the reference's PSNR counts the black
  background as well, which raises it). Two codes per rendered view:
  ``reconstruction`` (the code of the view itself, NeTePu's test) and
  ``novel`` (the code of another held-out pose seen by another camera:
  novel pose and view synthesis: the texture swapped onto another pose and
  view). Sets: ``heldout_poses`` (training cameras) and ``heldout_cameras``.
* **NeTePu's protocol** (:func:`nsd.evaluation.maps.image_psnr`): the same
  renders as 8-bit whole images (zero outside the ground-truth mask) against
  the whole ground-truth view, ``psnr_image_reconstruction`` and
  ``psnr_image_novel``.
* **Grids** (:func:`synthesis_grid`): for each texture, the source view whose
  code is used, then ground truth and rendering of novel poses/cameras.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor

from netepu.geometry.model import GeometryModel
from netepu.texture.crops import query_masked
from netepu.texture.data import TextureData
from netepu.texture.model import TextureModel
from nsd.cameras.batch import CameraBatch
from nsd.evaluation.maps import colour_psnr, image_psnr

__all__ = [
    "evaluate_colour",
    "heldout_codes",
    "heldout_reid_inputs",
    "render_colour",
    "synthesis_grid",
]


def _crop_batch(
    texture: TextureModel, data: TextureData, nnopcs: np.ndarray, views: np.ndarray, tex: np.ndarray
) -> Tensor:
    h = data.heldout
    rgb = torch.from_numpy(h["rgb"][views, tex]).float() / 255
    inside = torch.from_numpy(h["inside"][views])
    nn = torch.from_numpy(nnopcs[views].astype(np.float32))
    return texture.encoder_input(rgb, inside, nn)


@torch.no_grad()
def heldout_codes(
    texture: TextureModel, data: TextureData, nnopcs: np.ndarray, batch: int = 256
) -> np.ndarray:
    """mu of every held-out crop and texture, (E, T, d_z) float32 (eval mode)."""
    was = texture.training
    texture.eval()
    E, T = data.heldout["rgb"].shape[:2]
    views, tex = np.divmod(np.arange(E * T), T)
    out = []
    for s in range(0, E * T, batch):
        sl = slice(s, s + batch)
        out.append(texture.encode(_crop_batch(texture, data, nnopcs, views[sl], tex[sl]))[0])
    texture.train(was)
    return torch.cat(out).reshape(E, T, -1).numpy()


@torch.no_grad()
def heldout_reid_inputs(
    texture: TextureModel, data: TextureData, nnopcs: np.ndarray, codes: np.ndarray
) -> np.ndarray:
    """Re-identification inputs (E, T, reid_dims) of the held-out codes (E, T, d_z) from
    :func:`heldout_codes` (:meth:`TextureModel.reid_input`: the codes, with
    ``reid_colour`` followed by each crop's colour statistics)."""
    E, T = codes.shape[:2]
    if not texture.cfg.reid_colour:
        return codes
    views, tex = np.divmod(np.arange(E * T), T)
    flat = torch.from_numpy(codes.reshape(E * T, -1))
    out = []
    for s in range(0, E * T, 256):
        sl = slice(s, s + 256)
        x = _crop_batch(texture, data, nnopcs, views[sl], tex[sl])
        out.append(texture.reid_input(flat[sl], *texture.crop_colours(x)))
    return torch.cat(out).reshape(E, T, -1).numpy()


@torch.no_grad()
def render_colour(
    texture: TextureModel,
    geometry: GeometryModel,
    keypoints: Tensor,
    camera: CameraBatch,
    mask: Tensor,
    z: Tensor,
) -> Tensor:
    """Render colour at the mask pixels only.

    Args:
        keypoints: (n, K, 3); camera: batch n; mask: (n, H, W) bool; z: (n, d_z).

    Returns:
        (n, H, W, 3) clamped to [0, 1], zeros outside the mask.
    """
    n, H, W = mask.shape
    code = geometry.encode(keypoints)
    ctx = texture.prepare(z, code.z, code.features, keypoints, camera)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    uv = torch.stack([xs, ys], -1).reshape(1, -1, 2).float().expand(n, -1, -1)
    out = query_masked(lambda q: texture.query(ctx, q), uv, mask.reshape(n, -1))
    return out.reshape(n, H, W, 3).clamp(0, 1)


def _novel_source(data: TextureData) -> np.ndarray:
    """For every held-out view with full maps, a view of another pose and camera."""
    h = data.heldout
    pose, cam = h["pose"], h["camera"]
    src = []
    for v in h["psnr_view"]:
        other = np.nonzero((pose != pose[v]) & (cam != cam[v]) & ~h["heldout_camera"])[0]
        # deterministic: the first view of the next pose
        nxt = other[pose[other] == (pose[v] + 1) % (pose.max() + 1)]
        src.append(int((nxt if len(nxt) else other)[0]))
    return np.asarray(src)


@torch.no_grad()
def evaluate_colour(
    texture: TextureModel,
    geometry: GeometryModel,
    data: TextureData,
    codes: np.ndarray,
    max_views: int | None = None,
) -> dict[str, float]:
    """Colour PSNR of the held-out sets (see the module docstring).

    Args:
        codes: :func:`heldout_codes`, (E, T, d_z).
        max_views: evaluate only this many full-map views per set (quick checks).
    """
    was = texture.training
    texture.eval()
    h = data.heldout
    psnr_views = h["psnr_view"]
    src = _novel_source(data)
    T = codes.shape[1]
    out: dict[str, float] = {}
    for name, held in (("heldout_poses", False), ("heldout_cameras", True)):
        rows = np.nonzero(h["heldout_camera"][psnr_views] == held)[0]
        if max_views is not None:
            rows = rows[:max_views]
        res = {k: [] for k in ("reconstruction", "novel", "image_reconstruction", "image_novel")}
        for r in rows:
            v = int(psnr_views[r])
            kps = torch.from_numpy(h["keypoints"][[v] * T])
            cam = data.heldout_camera_tensors(np.array([v] * T))
            mask = torch.from_numpy(h["mask"][r])[None].expand(T, -1, -1)
            gt = torch.from_numpy(h["colour"][r]).float() / 255
            for kind, z in (("reconstruction", codes[v]), ("novel", codes[src[r]])):
                pred = render_colour(texture, geometry, kps, cam, mask, torch.from_numpy(z))
                res[kind].append(colour_psnr(pred, gt, mask))
                res[f"image_{kind}"].append(image_psnr(pred, gt, mask))
        for kind, vals in res.items():
            if vals:
                out[f"{name}/psnr_{kind}"] = float(torch.cat(vals).mean())
    texture.train(was)
    return out


@torch.no_grad()
def synthesis_grid(
    texture: TextureModel,
    geometry: GeometryModel,
    data: TextureData,
    codes: np.ndarray,
    held: bool,
    n_targets: int = 2,
    textures: list[int] | None = None,
) -> np.ndarray:
    """Novel pose / view synthesis grid.

    One row per texture: the source crop whose code is rendered, then
    ``n_targets`` pairs (ground truth, rendering) of other held-out poses seen by
    training cameras (``held=False``) or held-out cameras (``held=True``),
    cropped around the ground-truth mask.

    Returns:
        uint8 (rows * S, (1 + 2 n_targets) * S, 3) RGB with S the crop size.
    """

    h = data.heldout
    S = h["rgb"].shape[2]
    rows_all = np.nonzero(h["heldout_camera"][h["psnr_view"]] == held)[0]
    src = _novel_source(data)
    T = codes.shape[1]
    rows = []
    for t in textures if textures is not None else range(T):
        picks = rows_all[(np.arange(len(rows_all)) * 7 + t) % len(rows_all)][:n_targets]
        s0 = int(src[picks[0]])
        cells = [h["rgb"][s0, t]]
        for r in picks:
            v = int(h["psnr_view"][r])
            mask = torch.from_numpy(h["mask"][r])[None]
            pred = render_colour(
                texture,
                geometry,
                torch.from_numpy(h["keypoints"][[v]]),
                data.heldout_camera_tensors(np.array([v])),
                mask,
                torch.from_numpy(codes[s0, t][None]),
            )[0].numpy()
            x0, y0, side = h["window"][v]
            M = np.float32([[S / side, 0, -x0 * S / side], [0, S / side, -y0 * S / side]])
            for img in (h["colour"][r, t], (pred * 255 + 0.5).astype(np.uint8)):
                cells.append(
                    cv2.warpAffine(np.ascontiguousarray(img), M, (S, S), flags=cv2.INTER_AREA)
                )
        rows.append(np.concatenate(cells, 1))
    return np.concatenate(rows, 0)
