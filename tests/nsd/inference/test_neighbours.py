"""The Potts term on the mask ownership: a slow reference, hand-built cases, the wiring."""

from __future__ import annotations

import math

import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.inference.colour_models import ColourModels, window_compatibility
from nsd.inference.multiview import InferenceSettings
from nsd.inference.neighbours import (
    NEIGHBOUR_SIGMA,
    NEIGHBOUR_STEPS,
    NEIGHBOUR_WEIGHT,
    NeighbourAgreement,
    colour_affinities,
    neighbour_agreement,
)
from nsd.inference.single import decompose
from nsd.io.scene_data import SceneData
from nsd.model.build import build_model
from tests.nsd.training.test_train import tiny_cfg


def _reference(score, images, claim, weight, sigma, steps, mu):
    """Slowly, pixel by pixel: each mean-field round's message from the 8 neighbours inside
    the frame, both pixels claimed."""
    B, N, H, W = score.shape
    out = score.clone()
    for _ in range(steps):
        q = torch.softmax(out, 1)
        new = score.clone()
        for b in range(B):
            for y in range(H):
                for x in range(W):
                    if not claim[b, y, x]:
                        continue
                    for dy in (-1, 0, 1):
                        for dx in (-1, 0, 1):
                            yy, xx = y + dy, x + dx
                            if (dy, dx) == (0, 0) or not (0 <= yy < H and 0 <= xx < W):
                                continue
                            if not claim[b, yy, xx]:
                                continue
                            d2 = float(((images[b, :, y, x] - images[b, :, yy, xx]) ** 2).sum())
                            k = math.exp(-d2 / (2 * sigma**2))
                            for i in range(N):
                                for j in range(N):
                                    new[b, i, y, x] -= weight * mu[b, i, j] * k * q[b, j, yy, xx]
        out = new
    return out


def test_mean_field_matches_a_slow_reference_in_float64():
    g = torch.Generator().manual_seed(3)
    B, N, H, W = 2, 3, 6, 7
    score = torch.randn(B, N, H, W, generator=g, dtype=torch.float64)
    images = torch.rand(B, 3, H, W, generator=g, dtype=torch.float64)
    claim = torch.rand(B, H, W, generator=g) > 0.3
    mu = torch.rand(B, N, N, generator=g, dtype=torch.float64)
    mu = mu * (1 - torch.eye(N, dtype=torch.float64))
    fast = neighbour_agreement(score, images, claim, 0.7, 0.3, 3, mu)
    slow = _reference(score, images, claim, 0.7, 0.3, 3, mu)
    assert torch.allclose(fast, slow, atol=1e-12)
    potts = (1 - torch.eye(N, dtype=torch.float64)).expand(B, N, N)
    assert torch.allclose(neighbour_agreement(score, images, claim, 0.7, 0.3, 2),
                          _reference(score, images, claim, 0.7, 0.3, 2, potts), atol=1e-12)


def test_affinities_are_zero_off_the_claim_at_the_centre_and_one_within_a_colour():
    images = torch.zeros(1, 3, 4, 4)
    images[:, :, :, 2:] = 1.0  # a colour edge between columns 1 and 2
    claim = torch.ones(1, 4, 4, dtype=torch.bool)
    claim[0, 0, 0] = False
    k = colour_affinities(images, claim, 0.2)
    assert (k[:, 4] == 0).all()
    assert (k[0, :, 0, 0] == 0).all()  # an unclaimed pixel binds nothing
    assert k[0, 5, 2, 0] == 1.0  # right neighbour, one colour
    assert k[0, 5, 2, 1] == pytest.approx(math.exp(-3 / (2 * 0.2**2)))  # across the edge
    assert k[0, 5, 2, 3] == 0  # outside the frame


def _two_bodies(colour_edge: bool):
    """A 1 x 9 strip of two bodies, window 0 left of column 4, window 1 from it; column 4
    slightly favours window 0 in its own score."""
    score = torch.zeros(1, 2, 3, 9)
    score[0, 0, :, :4], score[0, 1, :, :4] = 3.0, -3.0
    score[0, 0, :, 5:], score[0, 1, :, 5:] = -3.0, 3.0
    score[0, 0, :, 4], score[0, 1, :, 4] = 0.3, 0.0
    images = torch.full((1, 3, 3, 9), 0.2)
    images[:, :, :, 4:] = 0.8 if colour_edge else 0.2  # column 4 has the right body's colour
    claim = torch.ones(1, 3, 9, dtype=torch.bool)
    return score, images, claim


def test_a_pixel_of_its_neighbours_colour_follows_them_and_an_edge_keeps_the_boundary():
    score, images, claim = _two_bodies(colour_edge=True)
    out = neighbour_agreement(score, images, claim, 1.0, 0.2, 3)
    assert (out.argmax(1)[0, :, 4] == 1).all()  # column 4 looks like the right body: joins it
    assert (out.argmax(1)[0, :, :4] == 0).all() and (out.argmax(1)[0, :, 5:] == 1).all()
    score, images, claim = _two_bodies(colour_edge=False)  # one colour: no edge to follow,
    out = neighbour_agreement(score, images, claim, 1.0, 0.2, 3)  # both sides pull alike
    assert (out.argmax(1)[0, :, 4] == 0).all()


def test_look_alikes_pay_nothing_and_weight_zero_changes_nothing():
    score, images, claim = _two_bodies(colour_edge=True)
    alike = torch.zeros(1, 2, 2)
    assert torch.equal(neighbour_agreement(score, images, claim, 1.0, 0.2, 3, alike), score)
    assert torch.equal(neighbour_agreement(score, images, claim, 0.0, 0.2, 3), score)
    assert torch.equal(NeighbourAgreement(1.0, 0.2, 0).rescore(score, images, claim), score)


def test_window_compatibility_from_kappa():
    kappa = torch.tensor([[0.0, 0.9, -0.4], [0.9, 0.0, 0.5], [-0.4, 0.5, 0.0]])
    seen = torch.tensor([[0, 40, 40], [40, 0, 3], [40, 3, 0]])
    ids = torch.tensor([0, 1, 2, 0])  # one frame: windows of individuals 0, 1, 2, 0
    mu = window_compatibility(kappa, seen, ids, 4)[0]
    assert mu[0, 1] == pytest.approx(0.9) and mu[1, 0] == pytest.approx(0.9)
    assert mu[0, 2] == 0.0  # one colour (kappa < 0): clipped
    assert mu[1, 2] == 1.0  # measured on too few pixels: Potts
    assert mu[0, 3] == 0.0 and (mu.diagonal() == 0).all()  # one individual


def test_decompose_changes_owners_not_the_foreground(tiny_scene):
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    model = build_model(tiny_cfg().model)
    views = torch.cat([data.views(t)[0] for t in range(4)])
    bgs = torch.cat([data.views(t)[1] for t in range(4)])
    for colour in (None, ColourModels(4.0, 8, 0.0)):
        off = decompose(model, views, bgs, min_weight=0.0, colour_models=colour)
        on = decompose(model, views, bgs, min_weight=0.0, colour_models=colour,
                       neighbours=NeighbourAgreement(50.0, 1.0))
        assert torch.equal(off.masks.sum(1), on.masks.sum(1))  # the same foreground,
        assert on.masks.sum(1).max() <= 1  # one owner each
        if colour is None:  # Potts: a strong term moves some owners
            assert not torch.equal(off.masks, on.masks)


def test_the_config_holds_the_modules_defaults_and_refuses_bad_values():
    settings = InferenceSettings.defaults()
    assert settings.neighbours == NeighbourAgreement(NEIGHBOUR_WEIGHT, NEIGHBOUR_SIGMA,
                                                     NEIGHBOUR_STEPS)
    for key, bad in (("neighbour_weight", -1.0), ("neighbour_weight", True),
                     ("neighbour_sigma", "x"), ("neighbour_sigma", float("inf"))):
        with pytest.raises(ConfigError, match=rf"inference\.{key}"):
            InferenceSettings.defaults(**{key: bad})
    with pytest.raises(ConfigError, match=r"inference\.neighbour_sigma"):
        InferenceSettings.defaults(neighbour_sigma=0.0)
    assert InferenceSettings.defaults(neighbour_sigma=0.0, neighbour_weight=0.0)
