"""Inference: switched-off windows cost nothing; frames without overlap skip occlusion terms."""

from __future__ import annotations

import torch

from nsd.cues.holes import Speckle
from nsd.inference.single import decompose
from nsd.model.build import build_model
from tests.nsd.training.test_train import tiny_cfg


def _model(presence_bias: float):
    model = build_model(tiny_cfg("model.detector.presence=true").model)
    with torch.no_grad():
        model.detector.head.bias.view(-1, 6)[0, 5] = presence_bias  # window 0 presence
        model.detector.head.bias.view(-1, 6)[1, 5] = 5.0  # window 1 on
    return model


def test_switched_off_window_is_not_encoded_or_decoded():
    model = _model(-5.0)
    calls = []
    model.encoder.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    images, bgs = torch.rand(3, 3, 24, 32), torch.rand(3, 3, 24, 32)
    dec = decompose(model, images, bgs, refine="none", min_area=0)
    assert calls == [3]  # one window per frame encoded, not 2
    assert not dec.active[:, 0].any()
    assert torch.equal(dec.crops[:, 0], torch.zeros_like(dec.crops[:, 0]))
    assert torch.equal(dec.app[:, 0], torch.zeros_like(dec.app[:, 0]))
    assert dec.masks[:, 0].abs().max() == 0
    # with the window on, it is encoded
    calls.clear()
    on = _model(5.0)
    on.encoder.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    decompose(on, images, bgs, refine="none")
    assert calls == [6]


def test_occlusion_reasoning_skipped_without_overlap():
    model = _model(5.0)
    with torch.no_grad():  # two small windows far apart: their masks cannot overlap
        b = model.detector.head.bias.view(-1, 6)
        b[:, 0:2] = -6.0  # minimum scale 0.2
        b[0, 2], b[1, 2] = -1.0, 1.0  # tx = 0.8 tanh(-+1) = -+0.61
    dec = decompose(model, torch.rand(2, 3, 24, 32), torch.rand(2, 3, 24, 32), refine="none")
    assert dec.occlusion_reasoning is False
    with torch.no_grad():
        model.detector.head.bias.view(-1, 6)[:, 2] = 0.0  # same place: overlapping
    dec = decompose(model, torch.rand(2, 3, 24, 32), torch.rand(2, 3, 24, 32), refine="none")
    assert dec.occlusion_reasoning is True


def test_residual_masks_have_their_speckle_filled():
    """A body whose colour matches the floor at a few pixels: the residual leaves them out of
    its mask; the default hole filling (nsd/cues/holes.py) gives them back, no speckle rules not."""
    model = _model(-5.0)
    bgs = torch.full((1, 3, 24, 32), 0.3)
    images = bgs.clone()
    images[..., 4:20, 8:24] = 0.8
    speckle = torch.zeros(24, 32, dtype=torch.bool)
    speckle[6:18:4, 10:22:4] = True
    images[..., speckle] = 0.3
    prior = torch.full((1, 24, 32), -1)
    prior[:, 4:20, 8:24] = 1  # window 1 owns the body
    kw = dict(owner_prior=prior, owner_bonus=10.0, min_weight=1.0)
    body = torch.zeros(24, 32, dtype=torch.bool)
    body[4:20, 8:24] = True
    plain = decompose(model, images, bgs, speckle=Speckle(0.0, 0.0), **kw).masks[0, 1] > 0.5
    assert torch.equal(plain, body & ~speckle)
    filled = decompose(model, images, bgs, **kw).masks[0, 1] > 0.5
    assert torch.equal(filled, body)


def test_residual_masks_give_another_subjects_islands_to_the_body_around_them():
    """Pixels of a body that the ownership gave to another subject (colours both coats share):
    the default island rule (nsd/cues/holes.py) gives them to the body around them."""
    model = _model(5.0)
    bgs = torch.full((1, 3, 24, 32), 0.3)
    images = bgs.clone()
    images[..., 4:20, 4:20] = 0.8  # window 1's body
    images[..., 4:20, 24:30] = 0.6  # window 0's body
    prior = torch.full((1, 24, 32), -1)
    prior[:, 4:20, 4:20] = 1
    prior[:, 4:20, 24:30] = 0
    islands = torch.zeros(24, 32, dtype=torch.bool)
    islands[8:16:4, 8:16:4] = True  # 4 pixels of window 1's body that window 0 owns
    prior[:, islands] = 0
    # a bonus above any log weight (>= log of the smallest float, -87): the prior decides
    kw = dict(owner_prior=prior, owner_bonus=200.0, min_weight=1.0)
    plain = decompose(model, images, bgs, speckle=Speckle(0.04, 0.0), **kw).masks[0] > 0.5
    assert plain[0][islands].all() and not plain[1][islands].any()
    clean = decompose(model, images, bgs, **kw).masks[0] > 0.5
    assert clean[1, 4:20, 4:20].all() and not clean[0, 4:20, 4:20].any()
    assert clean[0, 4:20, 24:30].all()  # window 0's own body stays
