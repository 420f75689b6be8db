"""Procedural textures: the pool, look-alike pairs, generated textures, value range."""

from __future__ import annotations

import itertools

import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.synth.body import make_individual
from nsd.synth.render import render_views
from nsd.synth.rigs import ring_rig
from nsd.synth.texture import LOOK_ALIKE_PAIRS, PATTERNS, POOL_SIZE, get_texture


@pytest.fixture(scope="module")
def surface() -> torch.Tensor:
    """NNOPCS values of the visible surface of a quadruped seen from 8 cameras, (M, 3)."""
    cow = make_individual("quadruped", 0)
    out = render_views(
        [cow], [cow.rest_pose()], ring_rig(8, radius=4.5, size=(64, 64)), background=False
    )
    return out["nnopcs"][out["instance"] >= 0].double()


def _colour_quantiles(texture_id: int, p: torch.Tensor) -> torch.Tensor:
    q = torch.linspace(0.05, 0.95, 19, dtype=torch.float64)
    return torch.quantile(get_texture(texture_id)(p), q, dim=0)


def test_pool_has_at_least_16_textures_of_several_patterns():
    assert POOL_SIZE >= 16
    patterns = {get_texture(i).pattern for i in range(POOL_SIZE)}
    assert {"solid", "patches", "spots", "stripes"} <= patterns <= set(PATTERNS)


def test_values_in_unit_range(surface):
    for i in [*range(POOL_SIZE), 16, 17, 1000]:
        a = get_texture(i)(surface)
        assert a.shape == surface.shape and a.min() >= 0 and a.max() <= 1


def test_look_alike_pairs_are_closer_than_any_other_pair(surface):
    """Look-alike pairs have nearly the same colour statistics, unlike every other pair,
    yet differ point by point (they are different individuals)."""
    desc = {i: _colour_quantiles(i, surface) for i in range(POOL_SIZE)}
    dist = {
        (i, j): (desc[i] - desc[j]).abs().mean().item()
        for i, j in itertools.combinations(range(POOL_SIZE), 2)
    }
    pairs = set(LOOK_ALIKE_PAIRS)
    worst_pair = max(dist[p] for p in pairs)
    best_other = min(v for k, v in dist.items() if k not in pairs)
    assert worst_pair < 0.5 * best_other, (worst_pair, best_other)
    for a, b in LOOK_ALIKE_PAIRS:
        diff = (get_texture(a)(surface) - get_texture(b)(surface)).abs().mean()
        assert diff > 0.005


def test_generated_textures_are_deterministic_and_new(surface):
    a1, a2, b = get_texture(37), get_texture(37), get_texture(38)
    assert torch.equal(a1(surface), a2(surface))
    assert (a1(surface) - b(surface)).abs().mean() > 0.01
    # unseen: far from every pool texture in colour statistics or layout
    for i in range(POOL_SIZE):
        assert (a1(surface) - get_texture(i)(surface)).abs().mean() > 0.005


def test_texture_is_a_function_of_nnopcs_only(surface):
    t = get_texture(5)
    perm = torch.randperm(surface.shape[0], generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(t(surface)[perm], t(surface[perm]))


def test_negative_id_rejected():
    with pytest.raises(ConfigError, match="texture"):
        get_texture(-1)
