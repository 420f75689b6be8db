"""The mask refiner: starts as the identity, changes masks only, differentiable, trained."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from nsd.core.errors import ConfigError
from nsd.io.scene_data import SceneData
from nsd.model.build import build_model
from nsd.model.focal_st import focal_bump
from nsd.model.mask_refiner import LOGIT_CLAMP, MaskRefiner
from nsd.training.task import NSDTask
from tests.nsd.training.test_train import tiny_cfg

REFINER = "model.mask_refiner.widths=[4,8]"


def _inputs(g, B=2, N=3, c=8, dtype=torch.float64):
    crops, bgs, rgb = (torch.rand(B, N, 3, c, c, generator=g, dtype=dtype) for _ in range(3))
    mask = torch.rand(B, N, 1, c, c, generator=g, dtype=dtype)
    return crops, bgs, rgb, mask


def test_an_untrained_refiner_returns_the_decoded_mask():
    refiner = MaskRefiner((4, 8)).double()
    g = torch.Generator().manual_seed(0)
    crops, bgs, rgb, mask = _inputs(g)
    mask[0, 0, 0, 0, 0], mask[0, 0, 0, 0, 1] = 0.0, 1.0  # clamped at both ends
    out = torch.sigmoid(refiner(crops, bgs, rgb, mask))
    torch.testing.assert_close(out, mask.clamp(LOGIT_CLAMP, 1 - LOGIT_CLAMP), rtol=0, atol=1e-12)


def test_the_refiner_grows_a_mask_by_at_most_grow_logits_and_carves_freely():
    torch.manual_seed(0)
    refiner = MaskRefiner((4, 8), grow=3.0).double()
    g = torch.Generator().manual_seed(5)
    crops, bgs, rgb, mask = _inputs(g)
    base = torch.logit(mask.clamp(LOGIT_CLAMP, 1 - LOGIT_CLAMP))
    for sign in (1.0, -1.0):
        torch.nn.init.constant_(refiner.out.bias, 50.0 * sign)
        delta = refiner(crops, bgs, rgb, mask) - base
        if sign > 0:  # G tanh(x / G) of a large x: G, never more
            assert delta.max() <= 3.0 + 1e-12 and delta.min() > 2.99
        else:  # carving is not bounded
            assert delta.max() < -40
    unbounded = MaskRefiner((4, 8), grow=None).double()
    torch.nn.init.constant_(unbounded.out.bias, 50.0)
    assert (unbounded(crops, bgs, rgb, mask) - base).min() > 40


@pytest.mark.parametrize("grow", [3.0, None])
def test_refiner_gradients_match_finite_differences(grow):
    torch.manual_seed(0)
    refiner = MaskRefiner((3, 4), grow).double()
    torch.nn.init.normal_(refiner.out.weight)  # not the zero start: every path counts
    g = torch.Generator().manual_seed(1)
    inputs = [t.requires_grad_() for t in _inputs(g, B=1, N=2, c=4)]
    inputs[3].data = inputs[3].data * 0.8 + 0.1  # inside the clamp: the logit is smooth there
    assert torch.autograd.gradcheck(refiner, inputs)


def test_the_refiner_sees_the_pixels_of_each_window_alone():
    """Window n's refined mask depends on window n's inputs and no other window's."""
    torch.manual_seed(0)
    refiner = MaskRefiner((4, 8)).double()
    torch.nn.init.normal_(refiner.out.weight)
    g = torch.Generator().manual_seed(2)
    crops, bgs, rgb, mask = _inputs(g)
    base = refiner(crops, bgs, rgb, mask)
    crops2 = crops.clone()
    crops2[1, 2] = torch.rand(3, 8, 8, generator=g, dtype=torch.float64)
    moved = refiner(crops2, bgs, rgb, mask)
    changed = (moved - base).abs().flatten(2).amax(-1)  # (B, N)
    assert changed[1, 2] > 1e-3
    changed[1, 2] = 0
    assert changed.max() == 0


def _render(model, g, hard=False):
    image, bg = (torch.rand(2, 3, 24, 32, generator=g, dtype=torch.float64) for _ in range(2))
    rotation = torch.linalg.qr(torch.randn(2, 3, 3, generator=g, dtype=torch.float64))[0]
    with torch.no_grad():
        target = model.windows(image, bg)
        source = model.windows(torch.rand(2, 3, 24, 32, generator=g, dtype=torch.float64), bg)
        return model.render(target, source, rotation, bg, hard=hard)


def test_a_model_with_an_untrained_refiner_renders_as_without():
    """With the max normalisation and a one-to-one association the refiner at its zero start
    changes the masks by no more than the clamp: the rendering is NSD's. (A soft association
    mixes masks, and the refiner's own normalisation then rescales the mixture.)"""
    plain = tiny_cfg("model.mask_normalisation=max", "model.mask_refiner.widths=[]")
    torch.manual_seed(0)
    without = build_model(plain.model).double().eval()
    torch.manual_seed(0)
    with_refiner = build_model(tiny_cfg("model.mask_normalisation=max", REFINER).model)
    with_refiner = with_refiner.double().eval()
    with_refiner.load_state_dict(without.state_dict(), strict=False)
    ours = _render(with_refiner, torch.Generator().manual_seed(3), hard=True)
    ref = _render(without, torch.Generator().manual_seed(3), hard=True)
    torch.testing.assert_close(ours.layers, ref.layers, rtol=0, atol=1e-12)
    torch.testing.assert_close(ours.window_mask, ref.window_mask, rtol=0, atol=3 * LOGIT_CLAMP)
    torch.testing.assert_close(ours.composite.weights, ref.composite.weights, rtol=0,
                               atol=3 * LOGIT_CLAMP)


def test_a_trained_refiner_changes_the_masks_and_not_the_colours():
    torch.manual_seed(0)
    model = build_model(tiny_cfg(REFINER).model).double().eval()
    ref = _render(model, torch.Generator().manual_seed(4))
    torch.nn.init.normal_(model.refiner.out.weight, std=3.0)
    ours = _render(model, torch.Generator().manual_seed(4))
    torch.testing.assert_close(ours.layers, ref.layers, rtol=0, atol=0)
    torch.testing.assert_close(ours.window_rgb, ref.window_rgb, rtol=0, atol=0)
    assert (ours.window_mask - ref.window_mask).abs().max() > 0.05
    # the normalisation still holds every window up: its pooled, pasted maximum is 1
    bump = focal_bump(*ours.window_mask.shape[-2:], dtype=torch.float64)
    pooled = torch.nn.functional.avg_pool2d((ours.window_mask * bump).flatten(0, 1), 3, 1, 1,
                                            count_include_pad=False)
    assert pooled.flatten(1).amax(1).min() >= 1 - 1e-9


def test_the_refiner_is_optimised_with_the_model(tiny_scene):
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    torch.manual_seed(0)
    task = NSDTask(tiny_cfg(REFINER), data)
    assert task.model.refiner is not None
    before = task.model.refiner.out.weight.detach().clone()
    out = task.training_step(0, np.random.default_rng(0))
    task.opt.zero_grad()
    out["loss"].backward()
    task.opt.step()
    assert not torch.equal(task.model.refiner.out.weight, before)


def test_refiner_config():
    assert build_model(tiny_cfg().model).refiner is None  # the shipped default: NSD's masks
    old = OmegaConf.to_container(tiny_cfg().model, resolve=True)
    del old["mask_refiner"]  # a checkpoint's config from before the refiner
    assert build_model(old).refiner is None
    with pytest.raises(ConfigError, match=r"mask_refiner\.widths"):
        build_model({**old, "mask_refiner": {"widths": [4, 0]}})
    with pytest.raises(ConfigError, match=r"mask_refiner\.grow"):
        build_model({**old, "mask_refiner": {"widths": [4], "grow": -1.0}})
    assert build_model({**old, "mask_refiner": {"widths": [4]}}).refiner.grow is None
    assert build_model(tiny_cfg(REFINER, "model.mask_refiner.grow=3").model).refiner.grow == 3.0
