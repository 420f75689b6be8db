"""Label-free presence target (nsd/priors/presence.py), the ungated compositor, its loss term."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.model.build import build_model
from nsd.priors.presence import marginal_presence_target, presence_target_loss, window_area
from tests.nsd.training.test_train import tiny_cfg

H = W = 16


def _square(y0: int, x0: int, size: int = 6, value: float = 1.0) -> torch.Tensor:
    m = torch.zeros(H, W)
    m[y0 : y0 + size, x0 : x0 + size] = value
    return m


def _scene():
    """Two individuals (squares of evidence); windows on A, empty, on A again (dup), on B."""
    evidence = (_square(1, 1) + _square(9, 9)).clamp(max=1)[None]
    masks = torch.stack([_square(1, 1), _square(1, 9), _square(1, 1, value=0.9), _square(9, 9)])
    area = torch.full((1, 4), 64.0)  # 8 x 8 px windows around the 6 x 6 px individuals
    return masks[None], evidence, area


def test_target_on_for_individuals_off_for_empty_and_duplicate():
    masks, evidence, area = _scene()
    target, gain = marginal_presence_target(masks, evidence, area, margin=0.1)
    assert target.tolist() == [[1.0, 0.0, 0.0, 1.0]]
    assert gain[0, 0].item() == pytest.approx(36 / 64)  # all of A, newly explained
    assert gain[0, 1].item() == 0.0  # empty window
    assert gain[0, 2].item() == pytest.approx(0.0, abs=1e-6)  # A already explained
    assert gain[0, 3].item() == pytest.approx(36 / 64)


@pytest.mark.parametrize("order", [[0, 1, 2, 3], [2, 0, 3, 1], [3, 2, 1, 0]])
def test_exactly_one_of_two_duplicates_stays_on_whatever_the_order(order):
    masks, evidence, area = _scene()
    masks[0, 2] = masks[0, 0]  # exact duplicate
    target, _ = marginal_presence_target(masks[:, order], evidence, area, margin=0.1)
    on = {o for o, t in zip(order, target[0].tolist(), strict=True) if t == 1}
    assert len(on & {0, 2}) == 1 and 3 in on and 1 not in on


def test_the_more_present_duplicate_stays_on():
    masks, evidence, area = _scene()
    for p_first, expected in ((0.9, [1.0, 0.0, 0.0, 1.0]), (0.2, [0.0, 0.0, 1.0, 1.0])):
        presence = torch.tensor([[p_first, 0.5, 0.6, 0.1]])
        target, _ = marginal_presence_target(masks, evidence, area, 0.1, presence)
        assert target.tolist() == [expected]  # window 3 is on however low its presence


def test_margin_is_relative_to_window_area():
    masks, evidence, area = _scene()
    small = torch.zeros_like(masks)
    small[0, 0] = masks[0, 0] * 0.1  # faint mask: explains 3.6 of 64 px
    target, gain = marginal_presence_target(small, evidence, area, margin=0.1)
    assert gain[0, 0].item() == pytest.approx(3.6 / 64)
    assert target.sum() == 0
    target, _ = marginal_presence_target(small, evidence, torch.full((1, 4), 16.0), 0.1)
    assert target[0, 0] == 1  # same mask, a window 4x smaller: on


def test_batch_items_are_independent():
    masks, evidence, area = _scene()
    empty = torch.zeros_like(evidence)
    target, _ = marginal_presence_target(
        torch.cat([masks, masks]), torch.cat([evidence, empty]), torch.cat([area, area])
    )
    assert target[0].tolist() == [1.0, 0.0, 0.0, 1.0]
    assert target[1].sum() == 0  # no foreground: every window off


def test_target_is_detached_and_the_loss_reaches_only_presence():
    masks, evidence, area = _scene()
    masks.requires_grad_(True)
    evidence.requires_grad_(True)
    target, gain = marginal_presence_target(masks, evidence, area)
    assert not target.requires_grad and not gain.requires_grad
    logits = torch.zeros(1, 4, dtype=torch.float64, requires_grad=True)
    presence_target_loss(torch.sigmoid(logits), target.double()).backward()
    # d BCE / d logit = (p - y) / (B N): pulls on-windows up, off-windows down
    assert torch.allclose(logits.grad, (0.5 - target.double()) / 4)
    assert masks.grad is None and evidence.grad is None


def test_bad_shapes_raise():
    masks, evidence, area = _scene()
    with pytest.raises(ValueError, match="evidence"):
        marginal_presence_target(masks, evidence[0], area)
    with pytest.raises(ValueError, match="area"):
        marginal_presence_target(masks, evidence, area[:, :2])


def test_window_area_in_pixels():
    boxes = torch.tensor([[[0.5, 0.25, 0.1, -0.3]]])  # half-sizes in [-1, 1] coordinates
    assert window_area(boxes, (24, 32)).item() == pytest.approx(0.5 * 32 * 0.25 * 24)


def _render(gate: str, presence_logit: float):
    torch.manual_seed(0)
    cfg = tiny_cfg("model.detector.presence=true", f"model.presence_gate={gate}")
    model = build_model(cfg.model)
    with torch.no_grad():
        model.detector.head.bias.view(-1, 6)[:, 5] = presence_logit
    model.eval()  # no decoder dropout: the two renderings differ only by presence
    images, bgs = torch.rand(2, 3, 24, 32), torch.rand(2, 3, 24, 32)
    win = model.windows(images, bgs)
    eye = torch.eye(3).expand(2, 3, 3)
    return model.render(win, win, eye, bgs, associate=False), win


def test_ungated_masks_ignore_presence_in_training():
    r_low, win = _render("none", -2.0)
    r_high, _ = _render("none", 2.0)
    assert torch.allclose(r_low.masks, r_high.masks)  # presence does not scale the masks
    assert torch.equal(r_low.masks, r_low.ungated_masks)
    assert not torch.allclose(win.det.presence, torch.ones_like(win.det.presence))
    # no image gradient reaches the presence when ungated
    assert not r_low.image.requires_grad or torch.autograd.grad(
        r_low.image.sum(), win.det.presence, allow_unused=True
    )[0] is None
    r_soft, _ = _render("soft", -2.0)
    p = torch.sigmoid(torch.tensor(-2.0))
    assert torch.allclose(r_soft.masks, r_soft.ungated_masks * p, atol=1e-6)


def test_hard_gate_keeps_only_present_windows_without_gradient():
    torch.manual_seed(0)
    model = build_model(tiny_cfg("model.detector.presence=true", "model.presence_gate=hard").model)
    with torch.no_grad():
        model.detector.head.bias.view(-1, 6)[0, 5] = -2.0  # window 0 off
        model.detector.head.bias.view(-1, 6)[1, 5] = 2.0  # window 1 on
    model.eval()
    images, bgs = torch.rand(2, 3, 24, 32), torch.rand(2, 3, 24, 32)
    win = model.windows(images, bgs)
    r = model.render(win, win, torch.eye(3).expand(2, 3, 3), bgs, associate=False)
    assert r.masks[:, 0].abs().max() == 0 and r.ungated_masks[:, 0].abs().max() > 0
    assert torch.equal(r.masks[:, 1], r.ungated_masks[:, 1])  # on: unscaled
    g = torch.autograd.grad(r.image.sum(), win.det.presence, allow_unused=True)[0]
    assert g is None or g.abs().max() == 0


def test_hard_gate_keeps_off_windows_out_of_the_other_view():
    """Bi-NVS under the hard gate: an off window of w fills no slot of v (and vice versa),
    so an on window is never rendered from an off window's decoding."""
    torch.manual_seed(0)
    model = build_model(tiny_cfg("model.detector.presence=true", "model.presence_gate=hard").model)
    with torch.no_grad():
        model.detector.head.bias.view(-1, 6)[0, 5] = -2.0  # window 0 off
        model.detector.head.bias.view(-1, 6)[1, 5] = 2.0  # window 1 on
    images, bgs = torch.rand(4, 3, 24, 32), torch.rand(4, 3, 24, 32)
    rv, rw, wv, ww = model(images[:2], images[2:], bgs[:2], bgs[2:], torch.eye(3).expand(2, 3, 3))
    assert (wv.det.presence[:, 0] < 0.5).all() and (ww.det.presence[:, 1] >= 0.5).all()
    for r in (rv, rw):
        assert r.association[..., 0].abs().max() == 0
        assert torch.allclose(r.association[..., 1], torch.ones(2, 2))
    soft = build_model(tiny_cfg("model.detector.presence=true", "model.presence_gate=soft").model)
    soft.load_state_dict(model.state_dict())
    rs, _, _, _ = soft(images[:2], images[2:], bgs[:2], bgs[2:], torch.eye(3).expand(2, 3, 3))
    assert rs.association[..., 0].min() > 0  # the soft gate keeps every source


def test_bad_presence_gate_raises():
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"presence_gate"):
        build_model(tiny_cfg("model.presence_gate=straight").model)


def test_marginal_group_ungates_and_trains_presence(tiny_scene):
    """prior_presence=marginal: hard gate, the BCE term is logged and moves only presence."""
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask

    assert tiny_cfg().model.presence_gate == "soft"  # fixed-N default unchanged
    cfg = tiny_cfg("model.detector.presence=true", "prior_presence=marginal")
    assert cfg.model.presence_gate == "hard"
    task = NSDTask(cfg, SceneData(tiny_scene, (32, 24), val_fraction=0.25))
    assert task.model.cfg.presence_gate == "hard"
    losses = task.training_step(0, np.random.default_rng(0))
    assert torch.isfinite(losses["presence_target"])
    on = float(losses["presence_target_on"])
    assert 0 <= on <= cfg.model.num_windows
    # the presence head bias gets gradient from the BCE term only
    task.opt.zero_grad()
    losses["pixel"].backward(retain_graph=True)
    g = task.model.detector.head.bias.grad
    assert g is None or g.view(-1, 6)[:, 5].abs().max() == 0
    task.opt.zero_grad()
    losses["presence_target"].backward()
    assert task.model.detector.head.bias.grad.view(-1, 6)[:, 5].abs().max() > 0


def test_unknown_presence_target_raises(tiny_scene):
    from nsd.core.errors import ConfigError
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask

    cfg = tiny_cfg("model.detector.presence=true", "prior_presence.target=oracle")
    with pytest.raises(ConfigError, match=r"prior_presence\.target"):
        NSDTask(cfg, SceneData(tiny_scene, (32, 24), val_fraction=0.25))


def test_cap_keeps_at_most_max_on_windows_in_presence_order():
    """Two halves of one individual both explain new foreground; a cap of 1 (the hull's
    count) keeps only the more present half on; a cap above the count changes nothing."""
    evidence = _square(2, 2, size=8)[None]
    left, right = torch.zeros(H, W), torch.zeros(H, W)
    left[2:10, 2:6], right[2:10, 6:10] = 1, 1
    masks, area = torch.stack([left, right])[None], torch.full((1, 2), 32.0)
    presence = torch.tensor([[0.4, 0.7]])
    free, _ = marginal_presence_target(masks, evidence, area, 0.2, presence)
    assert free.tolist() == [[1.0, 1.0]]
    capped, _ = marginal_presence_target(masks, evidence, area, 0.2, presence, torch.tensor([1]))
    assert capped.tolist() == [[0.0, 1.0]]
    loose, _ = marginal_presence_target(masks, evidence, area, 0.2, presence, torch.tensor([3]))
    assert loose.tolist() == free.tolist()
    none, _ = marginal_presence_target(masks, evidence, area, 0.2, presence, torch.tensor([0]))
    assert none.sum() == 0


def test_presence_cap_is_checked(tiny_scene):
    from nsd.core.errors import ConfigError
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask

    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    for bad, match in (
        ("prior_presence.cap=hull", r"prior_presence\.cap must be"),
        ("prior_proposal.source=single_view", r"cap=proposals needs"),
    ):
        cfg = tiny_cfg(
            "model.detector.presence=true",
            "prior_presence=marginal",
            "prior_presence.cap=proposals",
            bad,
        )
        with pytest.raises(ConfigError, match=match):
            NSDTask(cfg, data)


def test_capped_target_trains_and_never_exceeds_the_hull_count(tiny_scene):
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask

    cfg = tiny_cfg(
        "model.detector.presence=true", "prior_presence=marginal", "prior_presence.cap=proposals"
    )
    task = NSDTask(cfg, SceneData(tiny_scene, (32, 24), val_fraction=0.25))
    assert task.data.proposal_valid is not None
    losses = task.training_step(0, np.random.default_rng(0))
    assert torch.isfinite(losses["presence_target"])
    most = float(task.data.proposal_valid.sum(-1).max())
    assert 0 <= float(losses["presence_target_on"]) <= most


def test_ranked_target_keeps_the_count_most_present_windows():
    from nsd.priors.presence import ranked_presence_target

    p = torch.tensor([[0.2, 0.9, 0.5, 0.7], [0.1, 0.1, 0.3, 0.2], [0.6, 0.4, 0.8, 0.1]])
    got = ranked_presence_target(p, torch.tensor([2, 0, 4]))
    assert got.tolist() == [[0, 1, 0, 1], [0, 0, 0, 0], [1, 1, 1, 1]]
    # invariant: exactly min(count, N) on, and every on window is at least as present as any off
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        p = torch.rand(5, 4, generator=g)
        c = torch.randint(0, 6, (5,), generator=g)
        t = ranked_presence_target(p, c).bool()
        assert (t.sum(-1) == c.clamp(max=4)).all()
        lo = torch.where(t, p, torch.inf).min(-1).values
        hi = torch.where(~t, p, -torch.inf).max(-1).values
        assert (lo >= hi).all()
    with pytest.raises(ValueError, match="count must be"):
        ranked_presence_target(p, torch.tensor([1]))


def test_matching_gives_valid_proposals_to_active_windows():
    from nsd.cues.proposals import match_proposals

    boxes = torch.tensor([[[0.3, 0.3, 0.0, 0.0], [0.3, 0.3, 0.8, 0.0]]])
    props = torch.tensor([[[0.3, 0.3, 0.05, 0.0], [0.3, 0.3, -0.5, 0.5]]])
    valid = torch.tensor([[True, False]])
    assert match_proposals(boxes, props, valid).tolist() == [[0, 1]]  # the nearer window
    active = torch.tensor([[False, True]])
    assert match_proposals(boxes, props, valid, active).tolist() == [[1, 0]]


def test_hull_target_trains_the_most_present_windows(tiny_scene):
    from nsd.core.errors import ConfigError
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask

    cfg = tiny_cfg("model.detector.presence=true", "prior_presence=hull")
    assert cfg.model.presence_gate == "hard"
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    task = NSDTask(cfg, data)
    losses = task.training_step(0, np.random.default_rng(0))
    assert torch.isfinite(losses["presence_target"])
    assert 0 <= float(losses["presence_target_on"]) <= float(data.proposal_valid.sum(-1).max())
    single = tiny_cfg(
        "model.detector.presence=true", "prior_presence=hull", "prior_proposal.source=single_view",
        "prior_mask=off",
    )
    with pytest.raises(ConfigError, match="target=hull needs"):
        NSDTask(single, data)


def test_smoothed_counts_match_a_slow_running_median():
    from nsd.priors.presence import smoothed_counts

    g = torch.Generator().manual_seed(3)
    counts = torch.randint(0, 4, (23, 3), generator=g)
    valid = counts[..., None] > torch.arange(4)  # (T, V, k): the first `count` slots valid
    assert torch.equal(smoothed_counts(valid, 1), counts)
    for window in (3, 7, 15):
        h = window // 2
        padded = np.pad(counts.numpy(), ((h, h), (0, 0)), mode="edge")
        slow = np.stack([np.median(padded[t : t + window], 0) for t in range(len(counts))])
        assert np.array_equal(smoothed_counts(valid, window).numpy(), slow.astype(np.int64))
    # a merge lasting 3 frames in one view is removed by a 7-frame median, not by 5 frames
    dip = torch.tensor([4] * 6 + [3] * 3 + [4] * 6)[:, None]
    v = dip[..., None] > torch.arange(4)
    assert smoothed_counts(v, 7)[:, 0].eq(4).all()
    assert smoothed_counts(v, 5)[:, 0].eq(3).sum() == 3  # as long as half the window: kept
    for bad in (0, 2, -1):
        with pytest.raises(ValueError, match="odd number"):
            smoothed_counts(v, bad)


def test_scene_population_adds_back_individuals_merged_for_long():
    from nsd.priors.presence import smoothed_counts

    # 4 individuals in 2 views; in frames 10-29 two of them merge into one hull component
    # (slot 3 empty everywhere), and view 1 does not see slot 0 in frames 0-39
    T = 60
    valid = torch.ones(T, 2, 4, dtype=torch.bool)
    valid[10:30, :, 3] = False
    valid[:40, 1, 0] = False
    frame_only = smoothed_counts(valid, 5)
    assert frame_only[20].tolist() == [3, 2]  # longer than the window: the merge stays
    scene = smoothed_counts(valid, 5, scene_population=True)
    assert scene[20].tolist() == [4, 3]  # the merged individual is added back in each view
    assert scene[50].tolist() == [4, 4] and scene[0].tolist() == [4, 3]
    assert torch.equal(smoothed_counts(valid, 1, True)[5], frame_only[5])


def test_hull_target_uses_the_smoothed_count(tiny_scene):
    from nsd.core.errors import ConfigError
    from nsd.io.scene_data import SceneData
    from nsd.priors.presence import smoothed_counts
    from nsd.training.task import NSDTask

    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    cfg = tiny_cfg("model.detector.presence=true", "prior_presence=hull",
                   "prior_presence.count_window=3")
    task = NSDTask(cfg, data)
    assert torch.equal(data.counts, smoothed_counts(data.proposal_valid, 3))
    batch = data.pairs(np.array([0, 1]), np.array([0, 1]), np.array([1, 0]))
    assert batch.count_v.tolist() == [int(data.counts[0, 0]), int(data.counts[1, 1])]
    losses = task.training_step(0, np.random.default_rng(0))
    assert 0 <= float(losses["presence_target_on"]) <= float(data.counts.max())
    scene = tiny_cfg("model.detector.presence=true", "prior_presence=hull",
                     "prior_presence.count_population=scene")
    NSDTask(scene, data)
    assert torch.equal(data.counts, smoothed_counts(data.proposal_valid, 31, True))
    with pytest.raises(ConfigError, match="count_population"):
        NSDTask(tiny_cfg("model.detector.presence=true", "prior_presence=hull",
                         "prior_presence.count_population=everyone"), data)
    for bad in (2, 0):
        with pytest.raises(ConfigError, match="count_window"):
            NSDTask(tiny_cfg("model.detector.presence=true", "prior_presence=hull",
                             f"prior_presence.count_window={bad}"), data)


def test_hull_target_needs_no_other_proposal_prior(tiny_scene):
    """The hull's count is computed for the presence target even when every prior that
    reads the proposals is off."""
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask

    cfg = tiny_cfg("model.detector.presence=true", "prior_presence=hull",
                   "prior_proposal.weight=0", "prior_association.weight=0", "prior_depth=off")
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    task = NSDTask(cfg, data)
    assert data.counts is not None
    losses = task.training_step(0, np.random.default_rng(0))
    assert 0 <= float(losses["presence_target_on"]) <= float(data.counts.max())
