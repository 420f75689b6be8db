r"""Encoding a subject's texture from an image: the texture model's public API.

Public API (what the end-to-end pipeline calls)::

    texture_codes(texture, geometry, image, mask, keypoints, camera, window=None) -> Tensor
        # image (B, H, W, 3) float in [0, 1] or uint8: full frames or square crops
        # mask (B, H, W) bool: the subject's VISIBLE pixels (only they are read)
        # keypoints (B, K, 3) world; camera: K, R, t[, dist] with batch B
        # window (B, 3): (x0, y0, side) of a square crop in the camera's native
        #   pixels (pixel edges, as nsd.io.crops); None: image is the full frame
        # -> mu, (B, d_z): the texture code (the embedding) of each subject
    encode_texture(texture, image, mask, nnopcs) -> Tensor
        # the same from a precomputed (predicted) NNOPCS map (B, H, W, 3)

Both are ``torch.no_grad`` and put nothing but the code together; the model is
loaded with :func:`load_texture_model` from a ``netepu-train stage=texture``
checkpoint, which holds the frozen geometry model too.

Encoder input (:func:`encoder_crops`)
    The subject's visible pixels are cut out of the image with the square
    window around the mask's box (side ``max(w, h) (1 + 2 margin)``, as
    :func:`nsd.io.crops.square_crop_box`) and resampled to ``S x S``
    (``crop_size``): the masked image :math:`I \cdot M` and the mask are
    sampled bilinearly and divided, :math:`\tilde I = \mathrm{bilin}(I M) /
    \mathrm{bilin}(M)` where :math:`\mathrm{bilin}(M) > 1/2` and 0 elsewhere,
    so no pixel outside the mask reaches the encoder. The NNOPCS map is
    rendered by the frozen geometry model directly at the in-mask crop pixels
    (the renderer answers any query pixel), i.e. the encoder always sees
    *predicted* NNOPCS, in training and at inference (the reference trains on
    ground truth and tests on predictions). Channels: masked RGB, mask,
    NNOPCS (7; the RGB-only variant: 4).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from netepu.geometry.model import GeometryModel
from netepu.texture.crops import crop_grid, crop_windows, query_masked, sample_masked
from netepu.texture.model import TextureModel
from nsd.cameras.batch import CameraBatch

__all__ = [
    "encode_texture",
    "encoder_crops",
    "predicted_nnopcs",
    "predicted_surface",
    "surface_normals",
    "texture_codes",
]


# ----------------------------------------------------------------------------- inference
def _as_float_image(image: Tensor) -> Tensor:
    if image.dtype == torch.uint8:
        return image.float() / 255.0
    return image.float()


def predicted_nnopcs(
    geometry: GeometryModel, keypoints: Tensor, camera: CameraBatch, uv: Tensor, keep: Tensor
) -> Tensor:
    """NNOPCS rendered by the geometry model at kept pixels, clamped to [0, 1].

    Args:
        keypoints: (B, K, 3) world; camera: batch B.
        uv: (B, N, 2) pixels of the camera; keep: (B, N) bool.

    Returns:
        (B, N, 3), zeros where not kept.
    """
    ctx = _posed_context(geometry, keypoints, camera)
    out = query_masked(lambda q: geometry.query(ctx, q, ("nnopcs",))["nnopcs"], uv, keep)
    return out.clamp(0, 1)


def _posed_context(geometry: GeometryModel, keypoints: Tensor, camera: CameraBatch):
    """The geometry model's query context for keypoints (B, K, 3) seen by cameras (batch B)."""
    return geometry.prepare(geometry.encode(keypoints), camera, keypoints=keypoints)


def surface_normals(depth: Tensor, uv: Tensor, inside: Tensor, K: Tensor, R: Tensor) -> Tensor:
    r"""World-space unit normals of a depth crop on a regular pixel grid.

    Each crop pixel :math:`(u, v)` with camera depth :math:`Z` is back-projected,
    :math:`X = Z\, K^{-1} (u, v, 1)^\top` (lens distortion ignored: a crop spans a
    few dozen pixels), its tangents are the finite differences of :math:`X` along
    the crop's two axes (the mean of the forward and backward difference where
    both neighbours are inside, the one that is otherwise, none at a pixel with
    no inside neighbour on an axis), and the normal
    :math:`n = \partial_y X \times \partial_x X / \lVert\cdot\rVert`, flipped
    to face the camera (:math:`n \cdot X < 0`), is rotated to the world,
    :math:`n_w = R^\top n` (``R`` world-to-camera). With a light fixed in the
    world, Lambertian shading is a function of :math:`n_w` alone: what lets a
    texture code tell albedo from shading.

    Args:
        depth: (B, S, S) camera depth Z at the crop pixels.
        uv: (B, S, S, 2) their camera pixels (x, y).
        inside: (B, S, S) bool, pixels with a depth.
        K: (B, 3, 3) intrinsics; R: (B, 3, 3) world-to-camera rotation.

    Returns:
        (B, S, S, 3) unit normals; zeros outside or without a tangent on both axes.
    """
    ones = torch.ones_like(depth)
    rays = torch.einsum("bij,bhwj->bhwi", torch.linalg.inv(K), torch.cat([uv, ones[..., None]], -1))
    X = rays * depth[..., None]
    m = inside.to(X.dtype)

    def tangent(dim: int) -> tuple[Tensor, Tensor]:
        """Tangent along grid axis ``dim`` (1: rows, 2: columns) and where it exists."""
        n = X.shape[dim]
        step = X.narrow(dim, 1, n - 1) - X.narrow(dim, 0, n - 1)
        ok = m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1)
        step = step * ok[..., None]
        zero, zero_ok = torch.zeros_like(X.narrow(dim, 0, 1)), torch.zeros_like(m.narrow(dim, 0, 1))
        total = torch.cat([step, zero], dim) + torch.cat([zero, step], dim)  # forward + backward
        count = torch.cat([ok, zero_ok], dim) + torch.cat([zero_ok, ok], dim)
        return total / count.clamp_min(1)[..., None], count > 0

    tx, okx = tangent(2)
    ty, oky = tangent(1)
    n = torch.cross(ty, tx, dim=-1)
    n = n * torch.where((n * X).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(n.dtype)
    n = torch.nn.functional.normalize(n, dim=-1, eps=1e-12)
    world = torch.einsum("bji,bhwj->bhwi", R, n)
    return world * (inside & okx & oky)[..., None].to(X.dtype)


def predicted_surface(
    geometry: GeometryModel,
    keypoints: Tensor,
    camera: CameraBatch,
    uv: Tensor,
    keep: Tensor,
    normals: bool,
) -> Tensor:
    """The geometry model's surface at kept crop pixels: NNOPCS [+ world normals].

    Args:
        keypoints: (B, K, 3) world; camera: batch B.
        uv: (B, S, S, 2) crop pixels of the camera (a regular grid); keep: (B, S, S) bool.
        normals: also :func:`surface_normals` of the rendered depth.

    Returns:
        (B, S, S, 3) or (B, S, S, 6), zeros where not kept.
    """
    B, S1, S2 = keep.shape
    flat_uv, flat_keep = uv.reshape(B, S1 * S2, 2), keep.reshape(B, S1 * S2)
    if not normals:
        return predicted_nnopcs(geometry, keypoints, camera, flat_uv, flat_keep).reshape(
            B, S1, S2, 3
        )
    ctx = _posed_context(geometry, keypoints, camera)

    def both(q: Tensor) -> Tensor:
        out = geometry.query(ctx, q, ("depth", "nnopcs"))
        return torch.cat([out["nnopcs"].clamp(0, 1), out["depth"][..., None]], -1)

    out = query_masked(both, flat_uv, flat_keep).reshape(B, S1, S2, 4)
    K, R = camera.K.to(out.dtype), camera.R.to(out.dtype)
    n = surface_normals(out[..., 3], uv.to(out.dtype), keep, K, R)
    return torch.cat([out[..., :3], n], -1)


def encoder_crops(
    texture: TextureModel,
    image: Tensor,
    mask: Tensor,
    nnopcs: Tensor | Callable[[Tensor, Tensor], Tensor] | None,
    window: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
    """Cut the encoder's crops (see the module docstring).

    Args:
        texture: the model (crop size and margin).
        image: (B, H, W, 3) float in [0, 1] or uint8.
        mask: (B, H, W) bool visible pixels.
        nnopcs: a map (B, H, W, C_s) sampled like the image, or a function
            ``(uv (B, S, S, 2) camera pixels, keep (B, S, S)) -> (B, S, S, C_s)``
            that renders it at the crop pixels (:func:`predicted_surface`), or None
            (RGB-only models); C_s = ``cfg.surface_channels``.
        window: (B, 3) where ``image`` lies in the camera's native pixels
            (square crops); None: the image is the camera frame.

    Returns:
        ``(rgb, inside, nnopcs, grid)``: (B, S, S, 3), (B, S, S) bool,
        (B, S, S, C_s) or None, and the crop grid (B, S, S, 2) in image pixels.
    """
    img = _as_float_image(image)
    if img.ndim != 4 or img.shape[-1] != 3 or mask.shape != img.shape[:3]:
        raise ValueError(
            f"texture code: image must be (B, H, W, 3) and mask (B, H, W), got "
            f"{tuple(image.shape)} and {tuple(mask.shape)}"
        )
    mask = mask.bool()
    S = texture.cfg.crop_size
    grid = crop_grid(crop_windows(mask, texture.cfg.crop_margin), S)
    rgb, inside = sample_masked(img, mask, grid)
    nn_crop = None
    if texture.cfg.use_nnopcs:
        if nnopcs is None:
            raise ValueError(
                "this texture model reads NNOPCS: pass keypoints and cameras (or a map)"
            )
        if callable(nnopcs):
            cam_grid = grid
            if window is not None:
                H, W = img.shape[1:3]
                w = window.double()
                cam_grid = torch.stack(
                    [
                        w[:, None, None, 0] + (grid[..., 0] + 0.5) * w[:, None, None, 2] / W - 0.5,
                        w[:, None, None, 1] + (grid[..., 1] + 0.5) * w[:, None, None, 2] / H - 0.5,
                    ],
                    -1,
                )
            nn_crop = nnopcs(cam_grid.float(), inside)
        else:
            nn_crop, _ = sample_masked(nnopcs.float(), mask, grid)
        nn_crop = nn_crop * inside[..., None]
    return rgb, inside, nn_crop, grid


@torch.no_grad()
def encode_texture(
    texture: TextureModel, image: Tensor, mask: Tensor, nnopcs: Tensor | None = None
) -> Tensor:
    """Texture codes mu (B, d_z) from images, visible masks and NNOPCS maps (B, H, W, 3).

    ``nnopcs`` should be the geometry model's prediction (as in training);
    None for RGB-only models.
    """
    rgb, inside, nn_crop, _ = encoder_crops(texture, image, mask, nnopcs)
    texture.eval()
    return texture.encode(texture.encoder_input(rgb, inside, nn_crop))[0]


@torch.no_grad()
def texture_codes(
    texture: TextureModel,
    geometry: GeometryModel | None,
    image: Tensor,
    mask: Tensor,
    keypoints: Tensor | None,
    camera: CameraBatch | None,
    window: Tensor | None = None,
    return_crops: bool = False,
) -> Tensor | tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Texture codes of subjects from their visible pixels (see the module docstring).

    Args:
        texture, geometry: the models of a texture checkpoint (geometry may be
            None for RGB-only models).
        image: (B, H, W, 3) float in [0, 1] or uint8 frames or square crops.
        mask: (B, H, W) bool, the subject's visible pixels; nothing else is read.
        keypoints: (B, K, 3) world keypoints of each subject (None: RGB-only).
        camera: ``K, R, t[, dist]`` with batch B (the camera of each image).
        window: (B, 3) ``(x0, y0, side)`` of square crops in the camera's native
            pixels; None when ``image`` is the camera frame.
        return_crops: also return what the encoder read.

    Returns:
        mu, (B, d_z); with ``return_crops``: ``(mu, rgb (B, S, S, 3), inside (B, S, S),
        surface (B, S, S, C_s) or None)``, the surface being the predicted NNOPCS
        [+ world normals] at the crop pixels.
    """
    render = None
    if texture.cfg.use_nnopcs:
        if geometry is None or keypoints is None or camera is None:
            raise ValueError(
                "texture_codes: this model reads NNOPCS maps and needs the geometry "
                "model, keypoints and cameras"
            )
        geometry.eval()
        kps = keypoints.float()
        cam = CameraBatch.from_mapping(camera).to(torch.float32)

        def render(uv: Tensor, keep: Tensor) -> Tensor:
            return predicted_surface(geometry, kps, cam, uv, keep, texture.cfg.use_normals)

    rgb, inside, nn_crop, _ = encoder_crops(texture, image, mask, render, window)
    texture.eval()
    mu = texture.encode(texture.encoder_input(rgb, inside, nn_crop))[0]
    return (mu, rgb, inside, nn_crop) if return_crops else mu
