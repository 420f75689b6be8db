r"""Square crop windows around masks, and masked resampling onto the crop grid.

The encoder's input is cut with these (:func:`netepu.texture.encoding.encoder_crops`): only
pixels inside the mask reach the encoder.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from nsd.io.crops import square_crop_box
from nsd.ops.boxes import mask_boxes_xyxy

__all__ = ["crop_grid", "crop_windows", "query_masked", "sample_masked"]


# ----------------------------------------------------------------------------- crops
def crop_windows(mask: Tensor, margin: float | None) -> Tensor:
    """Square windows around the masks' boxes, or over the whole frame.

    Args:
        mask: (B, H, W) bool.
        margin: enlargement per side, as a fraction of the box's longer side; None: the
            whole frame, a square of side ``max(H, W)`` centred on the image (NeTePu's
            encoder reads the whole image), wherever the mask lies.

    Returns:
        (B, 3) ``(x0, y0, side)`` in pixels (pixel edges), float64.

    Raises:
        ValueError: a mask is empty (names the batch items).
    """
    empty = ~mask.flatten(1).any(1)
    if empty.any():
        raise ValueError(
            f"texture code: empty visible masks at batch items "
            f"{torch.nonzero(empty).flatten().tolist()}"
        )
    if margin is None:
        H, W = mask.shape[1:]
        side = max(H, W)
        frame = [(W - side) / 2, (H - side) / 2, side]
        return torch.tensor([frame] * len(mask), dtype=torch.float64, device=mask.device)
    boxes = mask_boxes_xyxy(mask).double()
    return torch.tensor(
        [square_crop_box([b[0], b[1], b[2] - b[0], b[3] - b[1]], margin) for b in boxes.tolist()],
        dtype=torch.float64,
        device=mask.device,
    )


def crop_grid(window: Tensor, size: int) -> Tensor:
    """Pixel centres of an ``size x size`` grid over square windows.

    Pixel ``(u, v)`` of the grid (centre at integers) sits at
    ``x = x0 + (u + 0.5) side / size - 0.5`` (and the same for y).

    Args:
        window: (B, 3) ``(x0, y0, side)``.
        size: S.

    Returns:
        (B, S, S, 2) ``(x, y)`` pixel coordinates, float64.
    """
    t = (torch.arange(size, dtype=torch.float64, device=window.device) + 0.5) / size
    x = window[:, None, 0] + t[None] * window[:, None, 2] - 0.5  # (B, S)
    y = window[:, None, 1] + t[None] * window[:, None, 2] - 0.5
    return torch.stack(torch.broadcast_tensors(x[:, None, :], y[:, :, None]), -1)


def sample_masked(values: Tensor, mask: Tensor, grid: Tensor) -> tuple[Tensor, Tensor]:
    r"""Bilinear samples of masked values that never read pixels outside the mask.

    :math:`\mathrm{bilin}(v M) / \mathrm{bilin}(M)` where :math:`\mathrm{bilin}(M) > 1/2`,
    0 elsewhere (outside the image counts as outside the mask).

    Args:
        values: (B, H, W, C) float.
        mask: (B, H, W) bool.
        grid: (B, S, S, 2) pixel coordinates (centre of pixel i at i).

    Returns:
        ``(sampled, inside)``: (B, S, S, C) and (B, S, S) bool.
    """
    _, H, W, C = values.shape
    m = mask.to(values.dtype)[:, None]
    x = torch.cat([(values * mask[..., None]).permute(0, 3, 1, 2), m], 1)
    g = grid.to(values.dtype)
    g = torch.stack([(g[..., 0] + 0.5) / W * 2 - 1, (g[..., 1] + 0.5) / H * 2 - 1], -1)
    s = F.grid_sample(x, g, mode="bilinear", padding_mode="zeros", align_corners=False)
    weight = s[:, C]
    inside = weight > 0.5
    out = torch.where(inside[:, None], s[:, :C] / weight.clamp(min=1e-6)[:, None], 0.0)
    return out.permute(0, 2, 3, 1), inside


def query_masked(query: Callable[[Tensor], Tensor], uv: Tensor, keep: Tensor) -> Tensor:
    """Evaluate ``query`` only at kept pixels (padded per batch item), zeros elsewhere.

    Args:
        query: ``uv (B, Q, 2) -> (B, Q, C)``.
        uv: (B, N, 2) pixels.
        keep: (B, N) bool.

    Returns:
        (B, N, C).
    """
    B, N = keep.shape
    counts = keep.sum(1)
    n = max(int(counts.max()), 1) if B else 1
    order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, :n]  # kept first
    pts = torch.gather(uv, 1, order[..., None].expand(B, n, 2))
    vals = query(pts)
    valid = torch.arange(n, device=keep.device)[None] < counts[:, None]
    vals = vals * valid[..., None]
    out = vals.new_zeros(B, N, vals.shape[-1])
    return out.scatter(1, order[..., None].expand(B, n, vals.shape[-1]), vals)
