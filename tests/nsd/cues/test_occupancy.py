"""Visual-hull proposals: individuals found in 3D, consistent slots across views, depth order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.cues import occupancy
from nsd.cues.clustering import cluster_individuals
from nsd.cues.occupancy import (
    candidate_individuals,
    contested_pixels,
    hull_individuals,
    hull_min_views,
    multiview_proposals,
    occupied_voxels,
    outer_voxels,
    owned_pixels,
    voxel_grid,
    working_volume,
)
from nsd.ops.boxes import box_iou_xywh, match
from nsd.synth import corner_rig, make_individual, render_views, sample_pose


@pytest.fixture(scope="module")
def two_people():
    rig = corner_rig(4, size=(96, 96))
    rng = np.random.default_rng(0)
    people = [make_individual("biped", identity=i, seed=i) for i in range(2)]
    poses = [
        sample_pose(p, rng, position=pos)
        for p, pos in zip(people, [(-0.6, 0.2), (0.5, -0.3)], strict=True)
    ]
    out = render_views(people, poses, rig, background=False)
    return rig, people, poses, out


def test_working_volume_contains_target():
    rig = corner_rig(4, size=(64, 64), target=(0.0, 0.0, 0.7))
    centre, half, up = working_volume(rig)
    np.testing.assert_allclose(centre, [0, 0, 0.7], atol=1e-6)
    np.testing.assert_allclose(up @ np.array([0, 0, 1.0]), 1.0, atol=0.1)
    assert 1.0 < half < 5.0


def test_hull_contains_bodies_and_clusters_them(two_people):
    rig, people, poses, out = two_people
    ev = out["instance"].ge(0).float()  # perfect foreground evidence (V, H, W)
    grid = voxel_grid(rig, ev.shape[-2:], 40)
    occ = occupied_voxels(ev, grid)
    pts = grid.centres[occ]
    roots = [p.keypoints3d(q)[0].numpy() for p, q in zip(people, poses, strict=True)]
    labels = cluster_individuals(pts, grid.up, grid.size, 2)
    centres = [pts[labels == j].mean(0).numpy() for j in range(2)]
    # each cluster's horizontal centre lies near one individual's root (the same one once)
    d = np.array([[np.linalg.norm((c - r)[:2]) for r in roots] for c in centres])
    assert min(d[0, 0] + d[1, 1], d[0, 1] + d[1, 0]) / 2 < 0.2


def test_proposals_match_visible_boxes_with_shared_slots_and_depth_order(two_people):
    rig, _, _, out = two_people
    ev = out["instance"].ge(0).float()
    grid = voxel_grid(rig, ev.shape[-2:], 40)
    boxes, depths, valid, owners, _ = multiview_proposals(ev, grid, 2)
    assert valid.all()
    H, W = ev.shape[-2:]
    slot_of = []
    for v in range(len(rig)):
        sx, sy, tx, ty = boxes[v].T * torch.tensor([0.75, 0.75, 1, 1])[:, None]
        px = torch.stack([(tx - sx + 1) * W / 2, (ty - sy + 1) * H / 2, sx * W, sy * H], -1)
        gt = out["boxes"][v].numpy()  # xyxy pixel edges
        gt = np.concatenate([gt[:, :2], gt[:, 2:] - gt[:, :2]], 1)
        iou = box_iou_xywh(px.numpy(), gt)
        pairs = match(iou)
        assert all(iou[p, g] > 0.5 for p, g in pairs) and len(pairs) == 2
        slot_of.append({g: p for p, g in pairs})
        # depth order of the proposals equals the individuals' order
        zgt = [float(out["depth"][v][out["instance"][v] == i].mean()) for i in range(2)]
        zp = [float(depths[v, slot_of[-1][i]]) for i in range(2)]
        assert (zgt[0] < zgt[1]) == (zp[0] < zp[1])
    # the slot of each individual is the same in every view
    assert all(s == slot_of[0] for s in slot_of)
    # most foreground pixels are owned by the right individual (the coarse hull blurs
    # ownership where the two overlap)
    right = sum(
        ((owners[v] == slot_of[0][i]) & (out["instance"][v] == i)).sum()
        for v in range(len(rig))
        for i in range(2)
    )
    assert right / out["instance"].ge(0).sum() > 0.75


def test_owned_pixels_front_wins():
    fg = torch.ones(1, 5, dtype=torch.bool)
    uv = torch.tensor([[1.0, 0.0], [3.0, 0.0], [2.0, 0.0], [2.0, 0.0]])
    depth = torch.tensor([2.0, 2.0, 5.0, 1.0])
    labels = torch.tensor([0, 1, 0, 1])
    owner = owned_pixels(fg, uv, depth, labels, 2, radius=0.6, reach=1.5)
    # pixel 2 is covered by voxels of both at depths 5 (label 0) and 1 (label 1): 1 wins
    assert owner[0].tolist() == [0, 0, 1, 1, 1]


def test_owned_pixels_cores_first():
    """A voxel outside its individual's core (a ghost in front of another body) gives way
    to a core voxel behind it, and still owns the pixels no core voxel reaches."""
    fg = torch.tensor([[True, True, True, True, False, True]])
    uv = torch.tensor([[1.0, 0.0], [3.0, 0.0], [2.0, 0.0], [2.0, 0.0], [5.0, 0.0]])
    depth = torch.tensor([2.0, 2.0, 5.0, 1.0, 1.0])
    labels = torch.tensor([0, 1, 0, 1, 1])
    outer = torch.tensor([False, False, False, True, True])
    front = owned_pixels(fg, uv, depth, labels, 2, radius=0.6, reach=1.5)
    cores = owned_pixels(fg, uv, depth, labels, 2, radius=0.6, reach=1.5, outer=outer)
    assert front[0].tolist() == [0, 0, 1, 1, -1, 1]
    assert cores[0].tolist() == [0, 0, 0, 1, -1, 1]


@pytest.mark.parametrize("count", [4, 8])
def test_cores_first_only_on_few_cameras(monkeypatch, count):
    """Up to CORE_MAX_VIEWS cameras each view's owners are :func:`owned_pixels` with the
    frame's :func:`outer_voxels`; above it, the front-most voxel's as before."""
    rig = corner_rig(count, size=(64, 64))
    rng = np.random.default_rng(3)
    people = [make_individual("biped", identity=i, seed=i) for i in range(2)]
    poses = [sample_pose(p, rng, position=pos)
             for p, pos in zip(people, [(-0.2, 0.0), (0.2, 0.0)], strict=True)]
    ev = render_views(people, poses, rig, background=False)["instance"].ge(0).float()
    grid = voxel_grid(rig, ev.shape[-2:], 32)
    idx, labels = hull_individuals(ev, grid, 2)
    shipped = multiview_proposals(ev, grid, 2, clustered=(idx, labels)).owners
    monkeypatch.setattr(occupancy, "CORE_MAX_VIEWS", 0)
    front = multiview_proposals(ev, grid, 2, clustered=(idx, labels)).owners
    idx, labels = idx[labels >= 0], labels[labels >= 0]
    outer = outer_voxels(grid.centres[idx], labels, 2)
    assert outer.any() and not outer.all()
    cores = torch.zeros_like(front)
    for v in range(count):
        vis = grid.inside[v, idx]
        z = grid.depth[v, idx[vis]]
        px = float(grid.size * grid.focal[v] / z.median())
        cores[v] = owned_pixels(ev[v] > 0.5, grid.uv[v, idx[vis]], z, labels[vis], 2,
                                occupancy.OWNER_RADIUS * px, occupancy.OWNER_REACH * px,
                                outer[vis])
    assert not torch.equal(cores, front)  # the case tells the two rules apart
    assert torch.equal(shipped, cores if count <= 4 else front)


def test_outer_voxels_known_values():
    """A cube of 27 voxels and a far one per individual: the far ones are outer (squared
    Mahalanobis distance ~22; the cube's corners ~3.2), nothing of an individual of fewer
    than 8 voxels is, nor a voxel without a label."""
    side = torch.tensor([-1.0, 0.0, 1.0])
    cube = torch.stack(torch.meshgrid(side, side, side, indexing="ij"), -1).reshape(-1, 3)
    far = torch.tensor([[8.0, 0, 0]])
    x = torch.cat([cube, far, cube + 20, far + 20, cube[:5] - 20, far - 20, far * 3])
    labels = torch.tensor([0] * 28 + [1] * 28 + [2] * 6 + [-1])
    got = outer_voxels(x, labels, 3, refits=0)
    assert got.nonzero().flatten().tolist() == [27, 55]
    # a looser spread keeps the far one in its core
    assert not outer_voxels(x, labels, 3, spread=100.0, refits=0).any()


def test_outer_voxels_refitted_from_the_core():
    """A cube of 27 voxels with a slab of 4 beside it (at x = 2 and 3), as the hull's excess
    lies against a body: the Gaussian of all 31 is pulled towards the slab and stretched
    along x, so the slab's nearest voxel (2, 0, 0) stays core (squared distance 2.5) and the
    four corners away from the slab are outer (4.7). Estimated again from those 24 core
    voxels, every slab voxel is outer ((2, 0, 0) now at 4.5) and so are the four corners on
    the slab's side (4.3); a second refit changes nothing more. The shipped default refits
    once."""
    side = torch.tensor([-1.0, 0.0, 1.0])
    cube = torch.stack(torch.meshgrid(side, side, side, indexing="ij"), -1).reshape(-1, 3)
    slab = torch.tensor([[2.0, 0, 0], [3.0, 0, 0], [2.0, 1, 0], [2.0, -1, 0]])
    x = torch.cat([cube, slab])
    labels = torch.zeros(31, dtype=torch.long)
    far_corners = [0, 2, 6, 8]  # x = -1, y = +-1, z = +-1
    near_corners = [18, 20, 24, 26]  # x = +1
    slab_ids = [27, 28, 29, 30]
    assert outer_voxels(x, labels, 1, refits=0).nonzero().flatten().tolist() == (
        far_corners + slab_ids[1:])
    once = outer_voxels(x, labels, 1, refits=1).nonzero().flatten().tolist()
    assert once == far_corners + near_corners + slab_ids
    assert outer_voxels(x, labels, 1, refits=2).nonzero().flatten().tolist() == once
    assert torch.equal(outer_voxels(x, labels, 1), outer_voxels(x, labels, 1, refits=1))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_outer", [False, True])
def test_owned_pixels_match_a_slow_reference(seed, with_outer):
    """Each foreground pixel goes to the front-most individual among the voxels projecting
    within ``radius`` of it (of those not outer first), else to the nearest voxel's within
    ``reach``, else to nobody: the k-d trees against every distance written out, pixel by
    pixel."""
    gen = torch.Generator().manual_seed(seed)
    fg = torch.rand(13, 17, generator=gen) > 0.3
    uv = torch.rand(60, 2, generator=gen) * torch.tensor([21.0, 17.0]) - 2.0
    depth = torch.rand(60, generator=gen) * 5 + 1
    labels = torch.randint(0, 4, (60,), generator=gen)
    outer = torch.rand(60, generator=gen) < 0.3 if with_outer else None
    got = owned_pixels(fg, uv, depth, labels, 4, radius=1.2, reach=2.5, outer=outer)
    want = torch.full_like(got, -1)
    rank = [0 if outer is None else int(outer[j]) for j in range(60)]
    for y in range(13):
        for x in range(17):
            if not fg[y, x]:
                continue
            d = [float(np.hypot(float(u) - x, float(v) - y)) for u, v in uv]
            near = [j for j in range(60) if d[j] <= 1.2]
            if near:
                want[y, x] = labels[min(near, key=lambda j: (rank[j], float(depth[j]), j))]
            elif min(d) <= 2.5:
                want[y, x] = labels[int(np.argmin(d))]
    assert torch.equal(got, want)
    assert (want >= 0).sum() < fg.sum() and len(set(want[want >= 0].tolist())) == 4


def test_owned_pixels_of_no_voxels_or_no_foreground_are_nobody_s():
    fg = torch.ones(3, 4, dtype=torch.bool)
    none = torch.zeros(0, dtype=torch.long)
    assert (owned_pixels(fg, torch.zeros(0, 2), torch.zeros(0), none, 2, 0.6, 1.5) == -1).all()
    one = torch.tensor([[1.0, 1.0]])
    got = owned_pixels(torch.zeros(3, 4, dtype=torch.bool), one, torch.ones(1),
                       torch.zeros(1, dtype=torch.long), 2, 0.6, 1.5)
    assert (got == -1).all()
    assert not candidate_individuals(fg, torch.zeros(0, 2), none, 2, 1.0).any()


def test_contested_pixels_match_a_slow_reference():
    """A pixel is contested when voxels of two or more individuals project within the band;
    background pixels never are."""
    gen = torch.Generator().manual_seed(0)
    fg = torch.rand(9, 11, generator=gen) > 0.3
    uv = torch.rand(40, 2, generator=gen) * torch.tensor([11.0, 9.0])
    labels = torch.randint(0, 3, (40,), generator=gen)
    got = contested_pixels(fg, uv, labels, 3, band=1.5)
    near = candidate_individuals(fg, uv, labels, 3, band=1.5)
    want = torch.zeros_like(fg)
    for y in range(9):
        for x in range(11):
            d = (uv - torch.tensor([x, y], dtype=uv.dtype)).norm(dim=1)
            close = set(labels[d <= 1.5].tolist()) if fg[y, x] else set()
            want[y, x] = len(close) >= 2
            assert set(torch.nonzero(near[:, y, x]).flatten().tolist()) == close, (y, x)
    assert torch.equal(got, want) and 0 < int(want.sum()) < int(fg.sum())


def test_contested_pixels_hand_built():
    fg = torch.ones(1, 6, dtype=torch.bool)
    uv = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [5.0, 0.0]])
    labels = torch.tensor([0, 0, 1, 1])
    # band 1: pixel 2 sees label 0 at x=1 and label 1 at x=3; pixel 4 sees only label 1
    assert contested_pixels(fg, uv, labels, 2, 1.0)[0].tolist() == [
        False, False, True, False, False, False]
    assert not contested_pixels(fg, uv, torch.zeros(4, dtype=torch.long), 2, 10.0).any()


def test_upper_bound_clusters_count_individuals_instead_of_cutting_them(two_people):
    """k = 4 windows for 2 individuals: with split (k individuals) the hull is cut into
    4 groups; as an upper bound (split=False) it keeps 2, and a low ghost is dropped."""
    rig, _, _, out = two_people
    ev = out["instance"].ge(0).float()
    grid = voxel_grid(rig, ev.shape[-2:], 40)
    pts = grid.centres[occupied_voxels(ev, grid)]
    assert len(set(cluster_individuals(pts, grid.up, grid.size, 4).tolist()) - {-1}) == 4
    bound = cluster_individuals(pts, grid.up, grid.size, 4, split=False)
    assert set(bound.tolist()) - {-1} == {0, 1}
    # a flat ghost away from both: two columns of two voxels each
    far = pts[:, :2].max(0).values + 1.0
    ghost = torch.stack(
        [torch.cat([far + torch.tensor([0.0, d * grid.size]), torch.tensor([h * grid.size])])
         for d in range(2) for h in range(2)]
    )  # fmt: skip
    both = torch.cat([pts, ghost])
    labels = cluster_individuals(both, grid.up, grid.size, 4, split=False)
    assert set(labels[: len(pts)].tolist()) - {-1} == {0, 1} and (labels[len(pts) :] == -1).all()
    # without the ratio it is kept as an individual of its own
    kept = cluster_individuals(both, grid.up, grid.size, 4, split=False, ghost_ratio=0.0)
    assert len(set(kept[len(pts) :].tolist())) == 1 and (kept[len(pts) :] >= 0).all()
    assert not set(kept[len(pts) :].tolist()) & set(kept[: len(pts)].tolist())
    valid = multiview_proposals(ev, grid, 4, split=False).valid
    assert (valid.sum(1) == 2).all()


@pytest.fixture(scope="module")
def touching_pair():
    """Two people side by side, 0.44 m apart, seen by a corner rig of 4 cameras."""
    rig = corner_rig(4, size=(96, 96))
    people = [make_individual("biped", identity=i, seed=i) for i in range(2)]
    rng = np.random.default_rng(3)
    poses = [sample_pose(p, rng, position=pos, heading=0.0)
             for p, pos in zip(people, [(0.0, -0.22), (0.0, 0.22)], strict=True)]
    return rig, render_views(people, poses, rig, background=False)


def test_a_hull_component_holding_two_touching_individuals_is_split_into_two_windows(
        touching_pair):
    """Two people side by side form one connected hull component; with the count known
    (k = 2) it is cut into two windows, each on one person in every view."""
    rig, out = touching_pair
    ev = out["instance"].ge(0).float()
    grid = voxel_grid(rig, ev.shape[-2:], 40)
    pts = grid.centres[occupied_voxels(ev, grid)]
    merged = cluster_individuals(pts, grid.up, grid.size, 2, split=False)
    assert set(merged[merged >= 0].tolist()) == {0}  # one component: the hull merged them
    props = multiview_proposals(ev, grid, 2, split=True)
    both = torch.nonzero(props.valid.all(1)).flatten().tolist()
    assert len(both) >= 3  # a camera looking along the pair sees one person hide the other
    purity = []
    for v in both:
        inst = out["instance"][v]
        counts = torch.stack([torch.bincount(inst[(props.owners[v] == j) & (inst >= 0)],
                                             minlength=2).float() for j in range(2)])
        assert (counts.sum(1) > 20).all()
        assert counts[0].argmax() != counts[1].argmax(), v  # one person each
        purity += (counts.max(1).values / counts.sum(1)).tolist()
    # a camera that sees one person partly behind the other gets mixed pixels (the hull
    # cannot carve between them along its rays): purity is high on average, not everywhere
    assert np.mean(purity) > 0.8, purity


def test_training_evidence_defaults_are_the_cue_defaults():
    """One source: the loss config's evidence settings are nsd.cues.evidence's constants."""
    from nsd.core.config import compose_app
    from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD

    cfg = compose_app("train")
    assert cfg.loss.evidence_threshold == EVIDENCE_THRESHOLD
    assert cfg.loss.evidence_softness == EVIDENCE_SOFTNESS


def test_hull_min_views_is_a_majority_of_the_cameras_unless_given():
    assert [hull_min_views(v) for v in (2, 3, 4, 5, 6, 8, 12)] == [2, 2, 3, 3, 4, 5, 7]
    assert hull_min_views(8, 3) == 3
    for bad in (1, 9):
        with pytest.raises(ConfigError, match="min_views"):
            hull_min_views(8, bad)


def test_voxels_seen_by_fewer_views_than_the_grids_minimum_are_not_carved():
    """Every pixel foreground: the hull is every voxel seen by enough cameras, so a voxel
    seen by two of four (the edges of the fields, where ghost bodies form) is kept with
    min_views=2 and dropped by the default majority (3 of 4)."""
    rig = corner_rig(4, size=(48, 48))
    ev = torch.ones(4, 48, 48)
    two = voxel_grid(rig, (48, 48), 24, min_views=2)
    auto = voxel_grid(rig, (48, 48), 24)
    assert (two.min_views, auto.min_views) == (2, 3)
    seen = two.inside.sum(0)
    assert (seen == 2).any() and (seen >= 3).any()
    assert torch.equal(occupied_voxels(ev, two), seen >= 2)
    assert torch.equal(occupied_voxels(ev, auto), seen >= 3)
    # an explicit argument still overrides the grid's
    assert torch.equal(occupied_voxels(ev, auto, min_views=2), seen >= 2)


def test_pixels_go_to_the_individual_whose_voxels_cover_them_not_to_a_fat_hull_in_front(
        touching_pair, monkeypatch):
    """The front individual's hull is fat along the rays of the cameras that do not carve
    it; with a wide ownership radius (1.5 voxels, before) it took the rims of the one behind.
    The default radius gives more of the pair's pixels to the right person in every view."""
    rig, out = touching_pair
    ev = out["instance"].ge(0).float()
    grid = voxel_grid(rig, ev.shape[-2:], 40)

    def accuracy() -> np.ndarray:
        owners = multiview_proposals(ev, grid, 2, split=True).owners
        acc = []
        for v in range(len(ev)):
            inst, own = out["instance"][v], owners[v]
            c = torch.stack([torch.bincount(inst[(own == j) & (inst >= 0)], minlength=2)
                             for j in range(2)])
            acc.append(max(c[0, 0] + c[1, 1], c[0, 1] + c[1, 0]).item() / (inst >= 0).sum())
        return np.array(acc)

    now = accuracy()
    monkeypatch.setattr("nsd.cues.occupancy.OWNER_RADIUS", 1.5)
    before = accuracy()
    assert now.mean() > before.mean() + 0.03, (now, before)
    assert (now > before - 0.02).all(), (now, before)
