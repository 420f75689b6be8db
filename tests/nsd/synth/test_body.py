"""Species, forward kinematics, individuals and their proportions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.synth.body import (
    GROUND_CLEARANCE,
    KEYPOINT_HOLD_MARGIN,
    Pose,
    Proportions,
    make_individual,
)
from nsd.synth.motion import sample_pose
from nsd.synth.nnopcs import ellipsoid_half_extents
from nsd.synth.skeleton import BIPED, QUADRUPED, SPECIES, get_species, joint_rotation
from tests.base import assert_close

SPECIES_NAMES = sorted(SPECIES)


class TestSpecies:
    def test_keypoint_counts(self):
        # H36M-like biped with 17 keypoints, NePuMoo-like quadruped with 25
        assert BIPED.num_keypoints == 17 and QUADRUPED.num_keypoints == 25
        assert BIPED.keypoint_names[:4] == ("hip", "right_hip", "right_knee", "right_foot")

    @pytest.mark.parametrize("name", SPECIES_NAMES)
    def test_tree_and_tables_are_consistent(self, name):
        sp = SPECIES[name]
        K = sp.num_keypoints
        assert sp.parents[0] == -1
        assert all(0 <= sp.parents[k] < k for k in range(1, K))  # parents precede children
        assert sp.rest.shape == (K, 3) and sp.joint_limits.shape == (K, 3, 2)
        assert np.all(sp.joint_limits[..., 0] <= sp.joint_limits[..., 1])
        assert len(sp.kpt_oks_sigmas) == K and len(sp.keypoint_groups) == K
        assert all(0 <= p.segment < K for p in sp.primitives)
        for p in sp.primitives:  # local axes are rotations
            q = np.asarray(p.axes)
            assert np.allclose(q @ q.T, np.eye(3), atol=1e-9) and np.linalg.det(q) > 0

    @pytest.mark.parametrize("name", SPECIES_NAMES)
    def test_every_keypoint_sits_in_a_body_part(self, name):
        """Keypoint visibility needs, for every keypoint, a primitive that contains it."""
        for identity in range(6):
            ind = make_individual(name, identity=identity, seed=3)
            body = ind.posed(ind.rest_pose())
            X = body.joints
            for k in range(ind.num_keypoints):
                p = ind.holders[k].nonzero().squeeze(-1)
                assert p.numel() > 0
                rel = (X[k] - body.centres[p]).unsqueeze(-2) @ body.axes[p]
                reach = (rel.squeeze(-2) / (body.radii[p] + KEYPOINT_HOLD_MARGIN)).norm(dim=-1)
                assert reach.min() <= 1.0, (name, ind.species.keypoint_names[k], reach)

    @pytest.mark.parametrize("name", SPECIES_NAMES)
    def test_the_mirror_index_reflects_the_rest_pose(self, name):
        """Relabelling left as right is the rest pose reflected through the body's midplane
        (the species are symmetric), and doing it twice is nothing."""
        sp = SPECIES[name]
        m = list(sp.mirror_index())
        np.testing.assert_allclose(sp.rest[m], sp.rest * [1.0, -1.0, 1.0], atol=1e-12)
        assert [m[i] for i in m] == list(range(sp.num_keypoints))
        assert m != list(range(sp.num_keypoints))
        if name == "biped":
            assert m[:7] == [0, 4, 5, 6, 1, 2, 3] and m[11] == 14 and m[9] == 9

    def test_unknown_species_names_the_key(self):
        with pytest.raises(ConfigError, match=r"species.*horse"):
            get_species("horse")


class TestKinematics:
    def test_joint_rotation_composition(self):
        a = torch.tensor([0.3, -0.7, 1.1], dtype=torch.float64)
        R = joint_rotation(a)
        rx = joint_rotation(torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64))
        ry = joint_rotation(torch.tensor([0.0, -0.7, 0.0], dtype=torch.float64))
        rz = joint_rotation(torch.tensor([0.0, 0.0, 1.1], dtype=torch.float64))
        assert_close(R, rz @ ry @ rx)
        assert_close(R @ R.T, torch.eye(3, dtype=torch.float64))
        # a positive pitch turns a downward bone backwards and a forward bone downwards
        pitch = joint_rotation(torch.tensor([0.0, 0.7, 0.0], dtype=torch.float64))
        assert (pitch @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))[0] < 0
        assert (pitch @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))[2] < 0

    @pytest.mark.parametrize("name", SPECIES_NAMES)
    def test_zero_angles_give_the_rest_pose(self, name):
        ind = make_individual(name, proportion_variation=0.0)
        k = ind.num_keypoints
        pose = Pose(torch.tensor([1.0, 2.0, 0.0]).double(), torch.tensor(0.0).double(),
                    torch.zeros(k, 3).double())  # fmt: skip
        X = ind.keypoints3d(pose)
        assert_close(X, torch.as_tensor(ind.species.rest) + torch.tensor([1.0, 2.0, 0.0]).double())

    def test_heading_rotates_about_the_vertical(self):
        ind = make_individual("quadruped", seed=1)
        p0 = ind.rest_pose()
        p1 = Pose(p0.translation, torch.tensor(np.pi / 2).double(), p0.angles)
        X0, X1 = ind.keypoints3d(p0), ind.keypoints3d(p1)
        # the nose points along +x at heading 0 and along +y at heading pi/2
        nose = ind.species.index("nose")
        assert X0[nose, 0] > 1.0 and abs(X0[nose, 1]) < 1e-9
        assert_close(X1[:, 0], -X0[:, 1])
        assert_close(X1[:, 1], X0[:, 0])
        assert_close(X1[:, 2], X0[:, 2])

    def test_bone_lengths_do_not_change_with_pose(self):
        ind = make_individual("biped", seed=2)
        rng = np.random.default_rng(0)
        X = torch.stack([ind.keypoints3d(sample_pose(ind, rng)) for _ in range(5)])
        parents = torch.tensor(ind.species.parents[1:])
        lengths = (X[:, 1:] - X[:, parents]).norm(dim=-1)
        rest = (ind.rest[1:] - ind.rest[parents]).norm(dim=-1)
        assert_close(lengths, rest.expand_as(lengths))

    def test_primitives_move_rigidly_with_their_segment(self):
        ind = make_individual("quadruped", seed=4)
        pose = sample_pose(ind, np.random.default_rng(1))
        body = ind.posed(pose)
        seg = ind.segments
        # centre relative to its segment joint, expressed in the segment frame, is pose-invariant
        rel = (
            body.rotations[seg].transpose(-1, -2) @ (body.centres - body.joints[seg])[..., None]
        )[..., 0]
        assert_close(rel, ind.rest_centres - ind.rest[seg])

    @pytest.mark.parametrize("name", SPECIES_NAMES)
    def test_place_on_ground_touches_the_ground(self, name):
        ind = make_individual(name, seed=5)
        pose = sample_pose(ind, np.random.default_rng(2))
        body = ind.posed(pose)
        half = ellipsoid_half_extents(body.axes, body.radii)
        assert_close(
            (body.centres[:, 2] - half[:, 2]).min(), torch.tensor(GROUND_CLEARANCE).double()
        )


class TestIndividuals:
    def test_mean_body_equals_species(self):
        ind = make_individual("biped", proportion_variation=0.0)
        assert_close(ind.rest, torch.as_tensor(BIPED.rest))
        assert ind.proportions.scale == 1.0

    def test_proportions_are_deterministic_and_vary(self):
        a = make_individual("biped", identity=1, seed=7)
        b = make_individual("biped", identity=1, seed=7)
        c = make_individual("biped", identity=2, seed=7)
        assert a.proportions == b.proportions and a.proportions != c.proportions
        assert_close(a.radii, b.radii)
        assert not torch.allclose(a.radii, c.radii)

    def test_leg_length_factor_scales_the_legs_only(self):
        legs = Proportions(scale=1.0, length={"leg": 1.1})
        ind = make_individual("biped", proportions=legs)
        mean = make_individual("biped", proportion_variation=0.0)
        knee, foot, sh, el = (
            BIPED.index(n) for n in ("left_knee", "left_foot", "left_shoulder", "left_elbow")
        )
        assert_close(
            (ind.rest[foot] - ind.rest[knee]).norm(),
            1.1 * (mean.rest[foot] - mean.rest[knee]).norm(),
        )
        assert_close((ind.rest[el] - ind.rest[sh]).norm(), (mean.rest[el] - mean.rest[sh]).norm())

    def test_texture_defaults_to_identity(self):
        assert make_individual("quadruped", identity=5).texture_id == 5
        assert make_individual("quadruped", identity=5, texture_id=20).texture.texture_id == 20

    def test_negative_variation_is_rejected(self):
        with pytest.raises(ConfigError, match="proportion_variation"):
            make_individual("biped", proportion_variation=-1)
