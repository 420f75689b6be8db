"""The individuals' colour models in the mask ownership (nsd/inference/colour_models.py)."""

from __future__ import annotations

import math

import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.inference.colour_models import (
    ColourModels,
    colour_log_likelihood,
    colour_separation,
    sure_owners,
)
from nsd.inference.multiview import InferenceSettings
from nsd.inference.single import decompose
from nsd.io.scene_data import SceneData
from nsd.model.build import build_model
from tests.nsd.training.test_train import tiny_cfg

RED, BLUE = (0.9, 0.1, 0.1), (0.1, 0.1, 0.9)


def _image(colours: list[tuple[float, float, float]]) -> torch.Tensor:
    """(1, 3, 1, W): one row of pixels of the given colours."""
    return torch.tensor(colours, dtype=torch.float32).T[None, :, None, :]


def test_sure_owners_need_the_margin():
    score = torch.tensor([[[[0.0, 0.0, 0.0]], [[-3.0, -1.0, 0.0]]]])  # (1, N=2, 1, 3)
    owner, sure = sure_owners(score, torch.ones(1, 1, 3, dtype=torch.bool), 2.0)
    assert owner.tolist() == [[[0, 0, 0]]]  # the first window on ties
    assert sure.tolist() == [[[True, False, False]]]
    # a pixel outside the candidates never teaches
    _, sure = sure_owners(score, torch.tensor([[[False, True, True]]]), 0.5)
    assert sure.tolist() == [[[False, True, False]]]


def test_likelihood_is_the_smoothed_histogram_of_the_sure_pixels():
    """Known values: bins 2 (K = 8 cells); window 0 owns 3 red pixels surely, window 1 one
    blue; p = (count + 1/2) / (n + K / 2)."""
    img = _image([RED, RED, RED, BLUE, BLUE])
    owner = torch.tensor([[[0, 0, 0, 1, 1]]])
    sure = torch.tensor([[[True, True, True, True, False]]])
    ll = colour_log_likelihood(img, owner, sure, 2, bins=2)
    assert ll.shape == (1, 2, 1, 5)
    red0, blue0 = math.log(3.5 / 7), math.log(0.5 / 7)
    red1, blue1 = math.log(0.5 / 5), math.log(1.5 / 5)
    expected = torch.tensor([[red0] * 3 + [blue0] * 2, [red1] * 3 + [blue1] * 2])
    assert torch.allclose(ll[0, :, 0], expected)
    # a window that owns nothing surely has the uniform likelihood 1 / K
    none = colour_log_likelihood(img, owner, torch.zeros_like(sure), 2, bins=2)
    assert torch.allclose(none, torch.full_like(none, math.log(1 / 8)))


def test_groups_pool_one_individuals_windows_across_views():
    """Window 1 of view 1 sees no pixel of its own surely; pooled with window 0 of view 0
    (one hull individual), it has that window's model; alone it has none."""
    img = torch.cat([_image([RED, RED, BLUE]), _image([BLUE, BLUE, RED])])
    owner = torch.tensor([[[0, 0, 1]], [[0, 0, 1]]])
    sure = torch.tensor([[[True, True, False]], [[True, True, False]]])
    groups = torch.tensor([[7, -1], [-1, 7]])
    pooled = colour_log_likelihood(img, owner, sure, 2, 2, groups)
    alone = colour_log_likelihood(img, owner, sure, 2, 2)
    # view 1, window 1: red is likely (view 0's window 0 taught it red), blue is not
    assert pooled[1, 1, 0, 2] == pytest.approx(math.log(2.5 / 6))
    assert pooled[1, 1, 0, 0] == pytest.approx(math.log(0.5 / 6))
    assert torch.allclose(alone[1, 1], torch.full((1, 3), math.log(1 / 8)))
    # windows left alone (-1) are not pooled with each other
    assert torch.equal(pooled[0, 1], alone[0, 1]) and torch.equal(pooled[1, 0], alone[1, 0])


def test_colour_models_settle_a_tie_by_colour():
    """Red pixels owned surely by window 0, blue by window 1, and a blue strip where the
    learned scores tie: the argmax gives the strip to window 0 (first on ties), the colour
    models give it to window 1, whose colour it has."""
    img = _image([RED] * 4 + [BLUE] * 4 + [BLUE] * 2)
    score = torch.zeros(1, 2, 1, 10)
    score[0, 1, 0, :4] = -5.0
    score[0, 0, 0, 4:8] = -5.0
    fg = torch.ones(1, 1, 10, dtype=torch.bool)
    models = ColourModels(weight=1.0, bins=4, margin=2.0)
    out = models.rescore(score, img, fg)
    assert out.argmax(1)[0, 0].tolist() == [0] * 4 + [1] * 6
    assert score.argmax(1)[0, 0, 8:].tolist() == [0, 0]
    # off, or with one window, the scores are untouched
    assert torch.equal(ColourModels(0.0, 4, 2.0).rescore(score, img, fg), score)
    assert torch.equal(models.rescore(score[:, :1], img, fg), score[:, :1])


def test_colour_models_change_owners_never_the_foreground(tiny_scene):
    """decompose with and without the colour models: the same foreground pixels are given
    to some window, and every pixel to exactly one."""
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    model = build_model(tiny_cfg().model)
    views = torch.cat([data.views(t)[0] for t in (0, 1)])
    bgs = torch.cat([data.views(t)[1] for t in (0, 1)])
    plain = decompose(model, views, bgs, min_weight=0.0)
    coloured = decompose(model, views, bgs, min_weight=0.0,
                         colour_models=ColourModels(4.0, 8, 0.0))
    assert torch.equal(plain.masks.sum(1), coloured.masks.sum(1))
    assert coloured.masks.sum(1).max() <= 1
    assert torch.equal(plain.raw_masks, coloured.raw_masks)


@pytest.mark.parametrize("kv", [{"colour_model": -1.0}, {"colour_model_bins": 1},
                                {"colour_model_bins": 33}, {"colour_model_bins": 2.5},
                                {"colour_model_bins": True}, {"colour_model_margin": -0.5},
                                {"colour_model_separation": 1.5},
                                {"colour_model_separation": -0.5},
                                {"colour_model_separation": True},
                                {"colour_model_separation": "high"}])
def test_wrong_colour_model_settings_name_their_key(kv):
    (key,) = kv
    with pytest.raises(ConfigError, match=f"inference.{key}"):
        InferenceSettings.defaults(**kv)


def test_settings_give_the_models_or_none():
    assert InferenceSettings.defaults(colour_model=0.0).colour_models is None
    on = InferenceSettings.defaults(colour_model=2.0, colour_model_bins=4,
                                    colour_model_margin=1.0,
                                    colour_model_separation=0.25).colour_models
    assert on == ColourModels(2.0, 4, 1.0, 0.25)


def test_greyscale_footage_separates_by_grey_level():
    """Greyscale cameras (equal channels, e.g. the mouse rigs' 1280 x 1024 footage) use
    only the grey cells; a dark and a light individual are still told apart: on a strip
    where window 1 leads by too little to be sure, a dark pixel goes to the dark window 0
    and a light one stays with the light window 1."""
    dark, light = (0.2, 0.2, 0.2), (0.8, 0.8, 0.8)
    score = torch.zeros(1, 2, 1, 10)
    score[0, 1, 0, :4] = -5.0  # window 0 owns the first four pixels surely
    score[0, 0, 0, 4:8] = -5.0  # window 1 the next four
    score[0, 1, 0, 8:] = 0.1  # the strip: window 1 ahead, not surely
    fg = torch.ones(1, 1, 10, dtype=torch.bool)
    models = ColourModels(weight=2.0, bins=16, margin=2.0)
    for strip, owner in ((dark, 0), (light, 1)):
        img = _image([dark] * 4 + [light] * 4 + [strip] * 2)
        assert models.rescore(score, img, fg).argmax(1)[0, 0].tolist() == (
            [0] * 4 + [1] * 4 + [owner] * 2)
    assert score.argmax(1)[0, 0, 8:].tolist() == [1, 1]  # without the models: window 1


GREEN = (0.1, 0.9, 0.1)


def test_separation_is_one_where_colours_tell_apart_and_minus_one_where_they_are_equal():
    """Known values, bins 2 (K = 8): every pixel sure. Window 0 red, window 1 blue: each
    pixel's own histogram, counted without it, still likes it best: a = 1, kappa = 1.
    Both windows 2 red + 2 blue: without itself a pixel's own cell counts 1 against the
    other window's 2 (1.5 / 7.5 < 2.5 / 8): a = 0, kappa = (0 - 1/2) / (1/2) = -1."""
    sure = torch.ones(1, 1, 8, dtype=torch.bool)
    apart = colour_separation(_image([RED] * 4 + [BLUE] * 4),
                              torch.tensor([[[0] * 4 + [1] * 4]]), sure, 2, 2)
    assert apart.tolist() == [1.0]
    alike = colour_separation(_image([RED, RED, BLUE, BLUE] * 2),
                              torch.tensor([[[0] * 4 + [1] * 4]]), sure, 2, 2)
    assert alike.tolist() == [-1.0]


def _slow_separation(img, owner, sure, n_windows, bins, instants):
    """kappa per frame by hand: loop over the sure pixels, histograms recounted without each."""
    B, _, H, W = img.shape
    q = (img * bins).long().clamp(max=bins - 1)
    cell = lambda b, y, x: tuple(int(v) for v in q[b, :, y, x])  # noqa: E731
    K = bins**3
    pix = [(b, y, x) for b in range(B) for y in range(H) for x in range(W) if sure[b, y, x]]
    out = []
    for b0 in range(B):
        mine = [p for p in pix if instants[p[0]] == instants[b0]]
        right = 0
        for p in mine:
            def p_of(w, skip, p=p):
                same = [r for r in pix if r[0] == p[0] and owner[r] == w and r != skip]
                hits = sum(cell(*r) == cell(*p) for r in same)
                return (hits + 0.5) / (len(same) + 0.5 * K)
            own = p_of(int(owner[p]), p)
            best = max(p_of(w, None) for w in range(n_windows) if w != owner[p])
            right += own > best
        n = max(2, len({int(owner[p]) for p in mine}))
        out.append((right / len(mine) - 1 / n) / (1 - 1 / n) if mine else 0.0)
    return out


def test_separation_matches_a_slow_count_and_pools_an_instants_frames():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(4, 3, 3, 5, generator=g)
    owner = torch.randint(0, 3, (4, 3, 5), generator=g)
    sure = torch.rand(4, 3, 5, generator=g) > 0.3
    alone = colour_separation(img, owner, sure, 3, 2)
    assert alone.tolist() == pytest.approx(
        _slow_separation(img, owner, sure, 3, 2, [0, 1, 2, 3]), abs=1e-6)
    instants = torch.tensor([0, 0, 1, 1])  # frames 0 and 1 are one instant's two views
    pooled = colour_separation(img, owner, sure, 3, 2, instants=instants)
    assert pooled[0] == pooled[1] and pooled[2] == pooled[3]


def test_individuals_of_one_colour_keep_the_learned_ownership():
    """Two windows, each owning red and green pixels surely, and a strip where window 1
    leads by too little to be sure: with ``separation`` the colour models (kappa -1 here)
    add nothing and the learned scores decide; without it, the strip's colour counts."""
    img = _image([RED, GREEN] * 4 + [RED] * 2)
    score = torch.zeros(1, 2, 1, 10)
    score[0, 1, 0, :3] = -5.0  # window 0 owns red, green, red surely
    score[0, 0, 0, 3:8] = -5.0  # window 1 owns green, red, green, red, green
    score[0, 1, 0, 8:] = 0.1  # the strip: window 1 ahead, not surely
    fg = torch.ones(1, 1, 10, dtype=torch.bool)
    gated = ColourModels(2.0, 2, 2.0, separation=0.2).rescore(score, img, fg)
    assert torch.equal(gated, score)
    assert not torch.equal(ColourModels(2.0, 2, 2.0).rescore(score, img, fg), score)
