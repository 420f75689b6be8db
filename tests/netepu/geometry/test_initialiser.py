"""The learned initialiser: its hull volume, heatmap targets, mapping back to the world,
checkpoints, learning, and its use by inverse rendering."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from netepu.geometry.initialiser import (
    InitialiserConfig,
    PoseInitialiser,
    initial_keypoints,
    load_initialiser,
    subject_volume,
)
from netepu.geometry.initialiser_training import heatmap_targets, render_bank, training_batch
from netepu.geometry.inverse import InverseSettings, invert_silhouettes, triangulate_centroids
from nsd.core.atomic import atomic_save_torch
from nsd.evaluation.pose import mpjpe
from nsd.ops.vectors import up_frame
from tests.base import BaseTester
from tests.netepu_world import own_renders, ring, toy_pose, trained_toy

CFG = InitialiserConfig(n_keypoints=3, radius=0.5, grid=16, extent=1.0, width=8)


def _rig(n: int = 3):
    return ring(n, size=(64, 64), radius=4.0, f=60.0).stacked(torch.float64)


class TestVolume(BaseTester):
    @pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.3, -0.5, 0.8)])
    def test_up_frame_is_orthonormal_with_up_last(self, up):
        B = up_frame(torch.tensor(up, dtype=torch.float64))
        self.assert_close(B.T @ B, torch.eye(3, dtype=torch.float64), atol=1e-12, rtol=0)
        u = torch.tensor(up, dtype=torch.float64)
        self.assert_close(B[:, 2], u / u.norm(), atol=1e-12, rtol=0)
        assert torch.linalg.det(B) > 0

    def test_full_empty_and_covered_silhouettes(self):
        """Every pixel the subject's: the hull is every voxel some view sees, share 1; no pixel
        the subject's but every pixel covered by another subject: the same hull, share 0;
        nothing at all: an empty hull."""
        cams = _rig()
        full, none = torch.ones(3, 64, 64, dtype=torch.bool), torch.zeros(3, 64, 64,
                                                                           dtype=torch.bool)
        anchor = torch.tensor([0.0, 0.0, 0.8])
        a = subject_volume(full, none, cams, anchor, CFG)
        b = subject_volume(none, full, cams, anchor, CFG)
        c = subject_volume(none, none, cams, anchor, CFG)
        assert a.shape == (2, 16, 16, 16)
        assert a[0].mean() > 0.9 and torch.equal(a[0], b[0])
        assert torch.equal(a[1], a[0]) and b[1].max() == 0
        assert c.max() == 0

    def test_a_point_seen_by_every_view_is_in_its_hull(self):
        """Silhouettes of 3x3 pixels about a point's projections: the voxel holding the point is
        in the hull with share 1; a voxel at the volume's corner is not."""
        cams = _rig()
        anchor = torch.tensor([0.1, -0.2, 0.8], dtype=torch.float64)
        offset = torch.tensor([0.13, -0.21, 0.27], dtype=torch.float64)
        point = anchor + offset
        from nsd.cameras.projection import project_points

        uv, _ = project_points(point.expand(3, 1, 3), cams.K, cams.R, cams.t)
        masks = torch.zeros(3, 64, 64, dtype=torch.bool)
        for v in range(3):
            x, y = (int(c) for c in uv[v, 0].floor())
            masks[v, y - 1:y + 2, x - 1:x + 2] = True
        vol = subject_volume(masks, torch.zeros_like(masks), cams, anchor, CFG)
        # up (0, 0, 1): the frame is the world's axes, voxel side 2 extent r / G
        i, j, k = ((offset / (CFG.extent * CFG.radius) + 1) * CFG.grid / 2).floor().long()
        assert vol[0, i, j, k] == 1 and vol[1, i, j, k] == 1
        assert vol[0, 0, 0, 0] == 0 and vol[0].sum() < 30


class TestHeatmaps(BaseTester):
    def test_targets_sum_to_one_and_their_mean_is_the_point(self):
        p = torch.rand(20, 3, dtype=torch.float64) * 1.7 - 0.85  # within the outer cell centres
        w = heatmap_targets(p, 8)
        cells = PoseInitialiser(InitialiserConfig(1, 1.0, grid=16)).cells.double()
        self.assert_close(w.sum(-1), torch.ones(20, dtype=torch.float64), atol=1e-12, rtol=0)
        self.assert_close(w @ cells, p, atol=1e-6, rtol=0)  # cells held in float32

    def test_a_cell_centre_is_one_cell(self):
        cells = PoseInitialiser(InitialiserConfig(1, 1.0, grid=16)).cells.double()
        w = heatmap_targets(cells[[5, 300]], 8)
        assert w[0, 5] == pytest.approx(1.0) and w[1, 300] == pytest.approx(1.0)
        assert float(w.max(-1).values.min()) == pytest.approx(1.0)


class _Fixed(torch.nn.Module):
    """A stand-in initialiser that always answers the same local keypoints."""

    def __init__(self, cfg: InitialiserConfig, local: torch.Tensor) -> None:
        super().__init__()
        self.cfg, self.local = cfg, local

    def forward(self, volume):
        return self.local[None].to(volume.dtype).expand(volume.shape[0], -1, -1)


def test_initial_keypoints_maps_the_volume_frame_to_the_world():
    """With up along z the volume's frame is the world's axes: x = anchor + extent r local."""
    local = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.25, 0.75], [-1.0, 1.0, 0.1]])
    anchor = torch.tensor([0.3, 0.2, 0.9])
    cams = _rig()
    masks = torch.ones(3, 64, 64, dtype=torch.bool)
    got = initial_keypoints(_Fixed(CFG, local), masks, torch.zeros_like(masks), cams, anchor)
    torch.testing.assert_close(got, anchor + CFG.extent * CFG.radius * local, atol=1e-6, rtol=0)


def test_checkpoint_round_trip_and_refusal(tmp_path):
    net = PoseInitialiser(CFG)
    atomic_save_torch({"format": "netepu-initialiser-v1", "config": CFG.to_dict(),
                       "state": net.state_dict()}, tmp_path / "init.pt")
    back = load_initialiser(tmp_path / "init.pt")
    assert back.cfg == CFG
    vol = torch.rand(2, 2, 16, 16, 16)
    torch.testing.assert_close(back(vol), net.eval()(vol))
    atomic_save_torch({"state": {}}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"other\.pt: not a NeTePu initialiser"):
        load_initialiser(tmp_path / "other.pt")


def test_training_batches_hold_the_true_keypoints_and_the_network_learns_them():
    """Rendered samples: targets in the volume's units, inside it; 60 Adam steps on one batch
    halve the distance (the network and its soft-argmax can learn)."""
    cfg = InitialiserConfig(17, 0.9, grid=16, extent=1.4, width=8)
    bank = render_bank("biped", 0.9, 3, 4, seed=0)
    assert bank.masks.shape == (3, 4, 128, 128) and bank.masks.any()
    vol, target = training_batch(bank, cfg, 4, np.random.default_rng(0))
    assert vol.shape == (4, 2, 16, 16, 16) and target.shape == (4, 17, 3)
    assert target.abs().max() < 1.0 and vol[:, 0].sum() > 0
    torch.manual_seed(0)
    net = PoseInitialiser(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    first = None
    for _ in range(60):
        logits = net.heatmap_logits(vol)
        dist = (torch.softmax(logits, -1) @ net.cells - target).norm(dim=-1).mean()
        ce = -(heatmap_targets(target, 8) * torch.log_softmax(logits, -1)).sum(-1).mean()
        first = float(dist.detach()) if first is None else first
        opt.zero_grad()
        (dist + 0.1 * ce).backward()
        opt.step()
    with torch.no_grad():
        last = float((net(vol) - target).norm(dim=-1).mean())
    assert last < 0.5 * first, (first, last)


def _toy_case():
    """The toy model's own silhouettes of a training pose in 3 views: the model, silhouettes,
    cameras, the pose's code, the silhouettes' triangulated centroid and an initialiser
    config for the model."""
    model, data, _ = trained_toy()
    views = data.evaluation["train"]
    cam = views.camera[[0, 2, 4]]
    own, code = own_renders(model, views.keypoints[0], cam, views.size)
    anchor = triangulate_centroids(own, cam).float()
    return (model, own, cam, code, anchor,
            InitialiserConfig(views.keypoints.shape[1], model.radius, grid=16, extent=2.0))


def test_inversion_refines_one_learned_start():
    """An initialiser that answers the true pose moved by 10 cm: inverse rendering runs its one
    start for init_steps steps (no templates screened) and lands on the pose."""
    model, own, cam, code, anchor, cfg = _toy_case()
    shifted = code.keypoints[0] + torch.tensor([0.1, 0.0, 0.0])
    local = (shifted - anchor) / (cfg.extent * cfg.radius)
    template = torch.from_numpy(toy_pose(np.random.default_rng(7))).float()[None]
    res = invert_silhouettes(model, own, cam, template,
                             InverseSettings(points_per_view=256, init_steps=30,
                                             init_templates=0),
                             initialiser=_Fixed(cfg, local))
    assert res.start_steps == 30 and len(res.start_losses) == 1
    assert mpjpe(res.keypoints, code.keypoints[0]) < 0.05


def test_the_pipeline_defaults_are_the_inversions():
    """conf/run.yaml's keypoint settings that are InverseSettings fields hold its defaults."""
    from dataclasses import fields
    from pathlib import Path

    from omegaconf import OmegaConf

    conf = OmegaConf.load(Path(__file__).parents[3] / "conf" / "run.yaml").netepu.keypoints
    shared = [f for f in fields(InverseSettings)  # (warm_steps: 0 there turns warm starts off)
              if f.name in ("steps", "point_budget", "init_steps", "init_poses",
                            "init_points_per_view")]
    for f in shared:
        assert conf[f.name] == f.default, f.name
    assert conf.init_templates == conf.travel_speed == conf.heading_tolerance == "auto"  # AUTO


def test_screened_templates_beside_a_wrong_learned_start_win():
    """A learned start 3 m above the body (no view sees it), alone, ends far off;
    with one screened template (the true pose's shape) beside it both run, the worse is
    dropped after half the steps (2 x 10 + 10 start-steps) and the template's fit is kept."""
    model, own, cam, code, anchor, cfg = _toy_case()
    far = code.keypoints[0] + torch.tensor([0.0, 0.0, 3.0])
    wrong = _Fixed(cfg, (far - anchor) / (cfg.extent * cfg.radius))
    alone = invert_silhouettes(model, own, cam, code.keypoints[0][None], InverseSettings(
        points_per_view=256, init_steps=20, init_templates=0), initialiser=wrong)
    assert mpjpe(alone.keypoints, code.keypoints[0]) > 0.1
    s = InverseSettings(points_per_view=256, init_steps=20, init_templates=1, init_headings=1)
    res = invert_silhouettes(model, own, cam, code.keypoints[0][None], s, initialiser=wrong)
    assert res.start_steps == 30 and len(res.start_losses) == 1
    assert mpjpe(res.keypoints, code.keypoints[0]) < 0.05
    # init_prune: the worse dropped after 5 steps (2 x 5 + 15 start-steps), the same winner
    early = invert_silhouettes(model, own, cam, code.keypoints[0][None],
                               replace(s, init_prune=5), initialiser=wrong)
    assert early.start_steps == 25 and len(early.start_losses) == 1
    assert mpjpe(early.keypoints, code.keypoints[0]) < 0.05


def test_only_the_first_init_poses_templates_are_screened_beside_a_learned_start(monkeypatch):
    """Beside a learned start the screening scores the first ``init_poses`` templates at
    ``init_headings`` headings (0: every template), and keeps ``init_templates`` of them."""
    from netepu.geometry import inverse

    model, own, cam, code, anchor, cfg = _toy_case()
    learned = _Fixed(cfg, (code.keypoints[0] - anchor) / (cfg.extent * cfg.radius))
    templates = code.keypoints[0] + 0.01 * torch.randn(5, *code.keypoints[0].shape,
                                                       generator=torch.Generator().manual_seed(0))
    screened, screen = [], inverse._screen
    monkeypatch.setattr(inverse, "_screen", lambda model, masks, cams, regions, z0, *a, **k: (
        screened.append(len(z0)) or screen(model, masks, cams, regions, z0, *a, **k)))
    for poses, expected in ((2, 2 * 3), (4, 4 * 3), (0, 5 * 3), (9, 5 * 3)):
        s = InverseSettings(points_per_view=64, init_steps=2, init_templates=2, init_headings=3,
                            init_poses=poses)
        res = invert_silhouettes(model, own, cam, templates, s, initialiser=learned)
        assert screened[-1] == expected, (poses, screened)
        assert res.start_steps == 3 * 1 + 1 * 1  # the learned start and 2 kept, then 1
