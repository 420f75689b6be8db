"""The pose code refitted on fresh poses (netepu/geometry/pose_code.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from netepu.geometry.data import DataConfig
from netepu.geometry.model import build_geometry_model
from netepu.geometry.pose_code import (
    PoseCodeSettings,
    fresh_poses,
    refit_pose_code,
    round_trip_error,
)
from nsd.synth.skeleton import get_species
from tests.netepu.texture.test_texture import K_BIPED, R_BIPED, TINY_GEOMETRY_DATA
from tests.netepu_world import TINY_MODEL

CFG = DataConfig.from_mapping({**TINY_GEOMETRY_DATA, "n_keypoints": K_BIPED})
PARENTS = get_species("biped").parents


def _model(seed: int = 0, blocks: int = 1):
    torch.manual_seed(seed)
    cfg = {**TINY_MODEL, "decoder": {**TINY_MODEL["decoder"], "n_blocks": blocks}}
    return build_geometry_model(cfg, K_BIPED, R_BIPED).eval()


def _bones(poses: torch.Tensor) -> torch.Tensor:
    """Bone lengths (n, K - 1) of poses (n, K, 3)."""
    return torch.stack([(poses[:, k] - poses[:, p]).norm(dim=-1)
                        for k, p in enumerate(PARENTS) if p >= 0], 1)


def test_fresh_poses_of_the_own_body_keep_its_bones_and_other_bodies_change_them():
    own = fresh_poses(CFG, 6, np.random.default_rng(0))
    world = fresh_poses(CFG, 6, np.random.default_rng(0), proportion_variation=1.0)
    assert own.shape == world.shape == (6, K_BIPED, 3)
    b_own, b_world = _bones(own), _bones(world)
    assert torch.allclose(b_own, b_own[:1].expand_as(b_own), atol=1e-5)  # one rigid body
    assert (b_world - b_world[:1]).abs().amax() > 1e-3  # every individual its own proportions
    again = fresh_poses(CFG, 6, np.random.default_rng(0))
    assert torch.equal(own, again)


@pytest.fixture(scope="module")
def refitted():
    """A tiny model before and after 150 steps, and the figures."""
    before, model = _model(), _model()
    figures = refit_pose_code(model, CFG, PoseCodeSettings(steps=150, pool=32, batch=16))
    return before, model, figures


def test_refit_moves_only_the_encoder_and_the_keypoint_decoder(refitted):
    before, after, _ = refitted
    moved = {name for (name, a), (_, b) in zip(before.named_parameters(),
                                              after.named_parameters(), strict=True)
             if not torch.equal(a, b)}
    assert moved, "nothing was trained"
    assert all(n.startswith(("encoder.", "decoder.mlp_pos.")) for n in moved), moved
    assert any(n.startswith("encoder.") for n in moved)
    assert any(n.startswith("decoder.mlp_pos.") for n in moved)
    assert all(p.requires_grad for p in after.parameters())  # flags restored
    assert not after.training


def test_refit_lowers_the_round_trip_error_on_held_out_poses(refitted):
    before, after, figures = refitted
    poses = fresh_poses(CFG, 40, np.random.default_rng(99), 1.0)
    assert float(round_trip_error(after, poses).mean()) < 0.7 * float(
        round_trip_error(before, poses).mean())
    assert figures["round_trip_own_after_mm"] < figures["round_trip_own_before_mm"]
    assert figures["round_trip_world_after_mm"] < figures["round_trip_world_before_mm"]


def test_the_feature_term_holds_the_features_and_the_refit_is_reproducible():
    # no point-transformer blocks: they read the decoded positions (detached), which the
    # feature term cannot hold; here the features are the code's alone
    settings = {"steps": 60, "pool": 32, "batch": 16}
    held, free, again = _model(blocks=0), _model(blocks=0), _model(blocks=0)
    kept = refit_pose_code(held, CFG, PoseCodeSettings(feature_weight=10.0, **settings))
    loose = refit_pose_code(free, CFG, PoseCodeSettings(feature_weight=0.0, **settings))
    assert kept["feature_change"] < 0.5 * loose["feature_change"]
    refit_pose_code(again, CFG, PoseCodeSettings(feature_weight=10.0, **settings))
    for a, b in zip(held.state_dict().values(), again.state_dict().values(), strict=True):
        assert torch.equal(a, b)
