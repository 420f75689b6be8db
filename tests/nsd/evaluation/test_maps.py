"""Colour PSNR: ours over the mask, NeTePu's over the whole 8-bit image."""

import math

import numpy as np
import torch

from nsd.evaluation.maps import colour_psnr, image_psnr


def _slow_image_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    """The reference's steps one pixel at a time: 8-bit render, zeros outside the mask."""
    H, W, _ = pred.shape
    total = 0.0
    for y in range(H):
        for x in range(W):
            for c in range(3):
                rec = int(min(max(pred[y, x, c], 0.0), 1.0) * 255 + 1e-6) if mask[y, x] else 0
                gt = int(min(max(target[y, x, c], 0.0), 1.0) * 255 + 1e-6)
                total += ((rec - gt) / 255) ** 2
    return 10 * math.log10(1 / (total / (H * W * 3)))


def test_known_values():
    target = torch.full((1, 4, 4, 3), 0.5)
    pred = torch.full((1, 4, 4, 3), 0.25)
    mask = torch.zeros(1, 4, 4, dtype=torch.bool)
    mask[:, :2] = True  # half of the image
    # ours: mean squared error 0.25^2 over the mask
    assert torch.allclose(colour_psnr(pred, target, mask), torch.tensor([-20 * math.log10(0.25)],
                                                                        dtype=torch.float64))
    # NeTePu's: 8 bits (127 and 63), the render is 0 outside the mask against 127 there
    mse = 0.5 * (64 / 255) ** 2 + 0.5 * (127 / 255) ** 2
    assert torch.allclose(image_psnr(pred, target, mask),
                          torch.tensor([-10 * math.log10(mse)], dtype=torch.float64))


def test_image_psnr_matches_a_slow_reference():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(3, 6, 5, 3, generator=g) * 1.2 - 0.1  # values outside [0, 1] are clamped
    target = torch.rand(3, 6, 5, 3, generator=g)
    mask = torch.rand(3, 6, 5, generator=g) > 0.4
    got = image_psnr(pred, target, mask)
    for i in range(3):
        want = _slow_image_psnr(pred[i].numpy(), target[i].numpy(), mask[i].numpy())
        assert abs(float(got[i]) - want) < 1e-9


def test_black_background_offsets_by_the_share_of_the_image():
    """On 8-bit colours over a black background the protocols differ by 10 log10(HW / |M|)."""
    g = torch.Generator().manual_seed(1)
    mask = torch.zeros(2, 8, 8, dtype=torch.bool)
    mask[0, 2:6, 1:7] = True
    mask[1, :, :3] = True
    q = lambda t: torch.floor(t * 255) / 255  # noqa: E731 (8-bit values)
    target = q(torch.rand(2, 8, 8, 3, generator=g)) * mask[..., None]
    pred = q(torch.rand(2, 8, 8, 3, generator=g))
    share = mask.flatten(1).double().mean(1)
    want = colour_psnr(pred, target, mask) - 10 * torch.log10(share)
    assert torch.allclose(image_psnr(pred, target, mask), want, atol=1e-9)
