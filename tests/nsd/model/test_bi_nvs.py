"""Bi-NVS renders both directions of its view pairs in one batch: the same as two renders."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nsd.model.build import build_model
from nsd.model.compositor import Composite
from tests.nsd.training.test_train import tiny_cfg


def _per_direction(model, image_v, image_w, background_v, background_w, rotation_vw):
    """The reference: each direction rendered on its own (v from w, then w from v)."""
    B = image_v.shape[0]
    both = model.windows(torch.cat([image_v, image_w]), torch.cat([background_v, background_w]))
    win_v, win_w = both.halves(B)
    if model.cfg.mode == "autoencoder":
        eye = torch.eye(3, dtype=image_v.dtype).expand(B, 3, 3)
        return (model.render(win_v, win_v, eye, background_v, associate=False),
                model.render(win_w, win_w, eye, background_w, associate=False))
    return (model.render(win_v, win_w, rotation_vw.transpose(-1, -2), background_v),
            model.render(win_w, win_v, rotation_vw, background_w))


@pytest.mark.parametrize("overrides", [[], ["model.mode=autoencoder"],
                                       ["model.detector.presence=true",
                                        "model.presence_gate=hard"]])
def test_one_batch_equals_two_renders(overrides):
    torch.manual_seed(0)
    model = build_model(tiny_cfg(*overrides).model).double().eval()  # no dropout
    g = torch.Generator().manual_seed(1)
    image_v, image_w, bg_v, bg_w = (torch.rand(3, 3, 24, 32, generator=g, dtype=torch.float64)
                                    for _ in range(4))
    rotation = torch.linalg.qr(torch.randn(3, 3, 3, generator=g, dtype=torch.float64))[0]
    with torch.no_grad():
        render_v, render_w, win_v, win_w = model(image_v, image_w, bg_v, bg_w, rotation)
        ref_v, ref_w = _per_direction(model, image_v, image_w, bg_v, bg_w, rotation)
    for ours, ref in ((render_v, ref_v), (render_w, ref_w)):
        for field in dataclasses.fields(ours):
            a, b = getattr(ours, field.name), getattr(ref, field.name)
            if isinstance(a, Composite):
                for x, y in zip(a, b, strict=True):
                    torch.testing.assert_close(x, y, rtol=0, atol=1e-12)
            elif isinstance(a, torch.Tensor):
                assert a.shape[0] == 3
                torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
            else:
                assert a == b
    # the views' own windows come back in their order
    torch.testing.assert_close(win_v.det.boxes, model.detector(image_v, bg_v).boxes,
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(win_w.det.boxes, model.detector(image_w, bg_w).boxes,
                               rtol=0, atol=1e-12)


def test_swapped_puts_the_second_half_first():
    torch.manual_seed(0)
    model = build_model(tiny_cfg().model).eval()
    images = torch.rand(4, 3, 24, 32)
    with torch.no_grad():
        both = model.windows(images, torch.rand(4, 3, 24, 32))
    swapped = both.swapped(2)
    assert torch.equal(swapped.app[:2], both.app[2:]) and torch.equal(swapped.app[2:], both.app[:2])
    assert torch.equal(swapped.det.boxes, both.det.boxes[[2, 3, 0, 1]])
