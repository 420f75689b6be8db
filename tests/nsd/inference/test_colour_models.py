"""The individuals' colour models in the mask ownership (nsd/inference/colour_models.py)."""

from __future__ import annotations

import math

import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.inference.colour_models import (
    ColourModels,
    colour_classes,
    colour_log_likelihood,
    colour_pair_separation,
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


def test_individuals_colour_cannot_tell_apart_are_joined():
    """Known values, bins 2 (K = 8), every pixel sure, 30 pixels each. Windows 0 and 1 both
    red and green half and half: without itself a pixel's own cell gives (14 + 1/2) / (29 +
    4) against the other's (15 + 1/2) / (30 + 4), so it never goes back (kappa -1): joined.
    Window 2 all blue: kappa 1 against both: apart. A cut at -1 joins none (kappa is
    never below -1)."""
    img = _image([RED, GREEN] * 30 + [BLUE] * 30)
    owner = torch.tensor([[[0, 0, 1, 1] * 15 + [2] * 30]])
    sure = torch.ones(1, 1, 90, dtype=torch.bool)
    assert colour_classes(img, owner, sure, 3, 2, 0.2).tolist() == [0, 0, 2]
    assert colour_classes(img, owner, sure, 3, 2, -1.0).tolist() == [0, 1, 2]
    # too few pixels between them: never compared, never joined
    few = torch.zeros_like(sure)
    few[0, 0, :12] = True  # 6 pixels each
    assert colour_classes(img, owner, few, 3, 2, 0.2).tolist() == [0, 1, 2]


def test_joined_classes_chain_and_groups_join_across_views():
    """Three windows of one colour in one view: all one class (0 joins 1, 1 joins 2). Two
    views of one instant, groups 5 and 6 in each: the classes are the groups'."""
    img = _image([RED, GREEN] * 45)
    owner = torch.tensor([[[0, 1, 2] * 30]])
    sure = torch.ones(1, 1, 90, dtype=torch.bool)
    assert colour_classes(img, owner, sure, 3, 2, 0.2).tolist() == [0, 0, 0]
    two = torch.cat([_image([RED, GREEN] * 15 + [BLUE] * 30)] * 2)
    owner2 = torch.tensor([[[0, 1] * 15 + [2] * 30]] * 2)
    groups = torch.tensor([[5, 5, 6], [7, 7, 6]])  # windows 0 and 1 of a view share a group
    cls = colour_classes(two, owner2, torch.ones(2, 1, 60, dtype=torch.bool), 3, 2, 0.2, groups)
    assert cls[2] == cls[5] and cls[0] == cls[1] and cls[0] != cls[2]


def test_individuals_of_one_colour_keep_the_learned_ownership():
    """Two windows, each owning red and green pixels surely in about equal shares, and a red
    strip where window 1 leads by too little to be sure: with ``separation`` the two share
    one colour model (kappa 0.13 < 0.2), which adds the same to both, and the learned
    scores decide; without it, window 0's few more red pixels take the strip."""
    img = _image([RED] * 17 + [GREEN] * 13 + [RED] * 13 + [GREEN] * 17 + [RED] * 2)
    score = torch.zeros(1, 2, 1, 62)
    score[0, 1, 0, :30] = -5.0  # window 0 owns 17 red and 13 green pixels surely
    score[0, 0, 0, 30:60] = -5.0  # window 1 13 red and 17 green (kappa 2 * 34 / 60 - 1)
    score[0, 1, 0, 60:] = 0.1  # the strip: window 1 ahead, not surely
    fg = torch.ones(1, 1, 62, dtype=torch.bool)
    joined = ColourModels(2.0, 2, 2.0, separation=0.2).rescore(score, img, fg)
    assert torch.allclose(joined[0, 0] - joined[0, 1], score[0, 0] - score[0, 1])
    assert joined.argmax(1)[0, 0, 60:].tolist() == [1, 1]
    apart = ColourModels(2.0, 2, 2.0).rescore(score, img, fg)
    assert apart.argmax(1)[0, 0, 60:].tolist() == [0, 0]


def _slow_pair_kappa(img, owner, sure, n_windows, bins):
    """kappa_ij by hand (each window alone): every sure pixel of i in a frame where j is,
    against j's histogram, i's recounted without it."""
    B, _, H, W = img.shape
    q = (img * bins).long().clamp(max=bins - 1)
    K = bins**3
    pix = [(b, y, x) for b in range(B) for y in range(H) for x in range(W) if sure[b, y, x]]
    cell = {p: tuple(int(v) for v in q[p[0], :, p[1], p[2]]) for p in pix}

    def prob(b, w, colour, skip=None):
        mine = [r for r in pix if r[0] == b and owner[r] == w and r != skip]
        return (sum(cell[r] == colour for r in mine) + 0.5) / (len(mine) + 0.5 * K)

    kappa = {}
    for b in range(B):
        for i in range(n_windows):
            for j in range(n_windows):
                if i == j:
                    continue
                lost = seen = 0
                for a, z in ((i, j), (j, i)):
                    for p in pix:
                        if p[0] == b and owner[p] == a:
                            seen += 1
                            lost += prob(b, z, cell[p]) >= prob(b, a, cell[p], p)
                kappa[(b * n_windows + i, b * n_windows + j)] = (1 - 2 * lost / max(seen, 1),
                                                                   seen)
    return kappa


def test_pair_separation_matches_a_slow_count():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 4, 5, generator=g)
    owner = torch.randint(0, 3, (2, 4, 5), generator=g)
    sure = torch.rand(2, 4, 5, generator=g) > 0.3
    kappa, seen = colour_pair_separation(img, owner, sure, 3, 2)
    for (i, j), (k, n) in _slow_pair_kappa(img, owner, sure, 3, 2).items():
        assert seen[i, j] == n and kappa[i, j].item() == pytest.approx(k, abs=1e-6), (i, j)
