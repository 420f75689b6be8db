"""Multi-view inference: windows fused with the visual hull, colour-aware ownership, slots."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.cues.clustering import ClusterTrack
from nsd.cues.evidence import foreground_evidence
from nsd.cues.occupancy import CONTEST_BAND, multiview_proposals
from nsd.inference.association_scores import association_scores
from nsd.inference.multiview import (
    InferenceSettings,
    carry_hull_track,
    decompose_views,
    fuse_detections,
    window_candidates,
    window_owners,
)
from nsd.inference.single import COLOUR_SIGMA, decompose, ownership
from nsd.io.scene_data import SceneData
from nsd.model.build import build_model
from nsd.model.detector import Detections
from tests.nsd.training.test_train import tiny_cfg


def _det():
    boxes = torch.tensor([[[0.4, 0.6, -0.5, 0.1], [0.3, 0.5, 0.4, 0.0]]])  # (V=1, N=2, 4)
    return Detections(boxes, torch.tensor([[0.3, -0.2]]), torch.ones(1, 2))


def _hull():
    # slot 0 lies near window 1, slot 1 near window 0: the matching must cross them
    boxes = torch.tensor([[[0.2, 0.4, 0.6, -0.1], [0.5, 0.9, -0.3, 0.2]]])
    return boxes, torch.tensor([[4.0, 6.0]])


def test_fusion_blends_centres_linearly_and_scales_geometrically():
    det = _det()
    hb, hd = _hull()
    fused, slots = fuse_detections(det, hb, hd, torch.ones(1, 2, dtype=torch.bool), 0.5)
    assert slots.tolist() == [[1, 0]]
    w0, h1 = det.boxes[0, 0], hb[0, 1]
    expect = [math.sqrt(w0[0] * h1[0]), math.sqrt(w0[1] * h1[1]), (w0[2] + h1[2]) / 2, 0.15]
    assert torch.allclose(fused.boxes[0, 0], torch.tensor(expect), atol=1e-6)
    assert fused.depths.tolist() == [[6.0, 4.0]]  # each window its individual's depth
    # the two ends of the blend: the detector's windows and the hull's
    f0, _ = fuse_detections(det, hb, hd, torch.ones(1, 2, dtype=torch.bool), 0.0, "detector")
    assert torch.allclose(f0.boxes, det.boxes) and torch.equal(f0.depths, det.depths)
    f1, _ = fuse_detections(det, hb, hd, torch.ones(1, 2, dtype=torch.bool), 1.0)
    assert torch.allclose(f1.boxes, hb[:, [1, 0]], atol=1e-6)


def test_invalid_individual_keeps_the_window_and_the_views_depth_units():
    det = _det()
    hb, hd = _hull()
    valid = torch.tensor([[True, False]])  # only slot 0 (window 1's) is valid
    fused, slots = fuse_detections(det, hb, hd, valid, 1.0)
    assert slots.tolist() == [[-1, 0]]
    assert torch.equal(fused.boxes[0, 0], det.boxes[0, 0])
    assert torch.allclose(fused.boxes[0, 1], hb[0, 0])
    # one window has no hull depth: the view keeps the detector's depths for both
    assert torch.equal(fused.depths, det.depths)


def test_ownership_prefers_the_subject_whose_colour_matches():
    weights = torch.tensor([0.6, 0.4]).view(1, 2, 1, 1)
    image = torch.tensor([0.0, 0.0, 0.0]).view(1, 3, 1, 1)  # a black pixel
    layers = torch.stack([torch.ones(3), torch.zeros(3)]).view(1, 2, 3, 1, 1)  # white, black
    assert torch.allclose(ownership(weights, layers, image, 0.0).exp(), weights)
    o = ownership(weights, layers, image, 0.2)
    assert o.argmax(1).item() == 1
    assert o[0, 0].item() == pytest.approx(math.log(0.6) - 3 / (2 * 0.04))
    assert o[0, 1].item() == pytest.approx(math.log(0.4))
    # a tiny scale cannot underflow both scores to 0: the closer colour still wins
    grey = torch.stack([torch.full((3,), 0.9), torch.full((3,), 0.8)]).view(1, 2, 3, 1, 1)
    assert ownership(weights, grey, image, 0.01).argmax(1).item() == 1


def test_slot_bonus_is_added_only_for_the_same_valid_individual(tiny_scene):
    cams = SceneData(tiny_scene, (32, 24)).cameras
    model = build_model(tiny_cfg().model)
    app = torch.randn(2, 2, model.encoder.app_dims)
    dec = SimpleNamespace(
        windows=torch.tensor([[0.4, 0.5, -0.2, 0.0], [0.3, 0.4, 0.3, 0.1]]).expand(2, 2, 4),
        app=app,
        slots=torch.tensor([[0, -1], [-1, 0]]),
    )
    base = association_scores(model, dec, cams, (24, 32), 0, 1, 0.0)
    bonus = association_scores(model, dec, cams, (24, 32), 0, 1, 2.5)
    diff = bonus - base
    assert torch.allclose(diff, torch.tensor([[0.0, 2.5], [0.0, 0.0]]))


@pytest.mark.parametrize(
    "kv",
    [
        {"views": "both"},
        {"window_blend": 1.5},
        {"depth": "stereo"},
        {"slot_bonus": -1.0},
        {"resolution": 2},
        {"min_views": 1},
        {"min_views": "most"},
        {"colour_sigma": -0.1},
    ],
)
def test_wrong_settings_name_their_key(kv):
    (key,) = kv
    with pytest.raises(ConfigError, match=f"inference.{key}"):
        InferenceSettings.defaults(**kv)


def test_decompose_defaults_to_the_configs_colour_agreement():
    """decompose without settings (views=single callers, tools) and the inference config
    agree on the ownership's colour agreement: one value, chosen in benchmarks/ownership.md."""
    assert InferenceSettings.defaults().colour_sigma == COLOUR_SIGMA


def test_unknown_setting_and_single_camera_are_clear_errors(tiny_scene):
    with pytest.raises(ConfigError, match="no setting 'blend'"):
        InferenceSettings.from_config({"blend": 0.5})
    for key in ("hull_ownership", "hull_contested", "colour_sigma"):
        with pytest.raises(ConfigError, match=f"inference.{key} must be >= 0"):
            InferenceSettings.from_config({key: -1.0})
    data = SceneData(tiny_scene, (32, 24))
    one = data.rig.select(data.rig.names[:1])
    with pytest.raises(ConfigError, match="at least 2 cameras"):
        InferenceSettings.defaults().grid(one, data.frame_hw)


def test_no_blend_and_detector_depths_reproduce_single_image_inference(tiny_scene):
    """With the windows and depths left as the detector's, multi-view inference must give
    exactly NSD's single-image decomposition, plus the slots."""
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    model = build_model(tiny_cfg().model)
    views = torch.cat([data.views(t)[0] for t in (0, 1)])
    bgs = torch.cat([data.views(t)[1] for t in (0, 1)])
    V = data.num_views
    same = InferenceSettings.defaults(window_blend=0.0, depth="detector", resolution=16,
                                      hull_ownership=0.0, hull_contested=0.0, colour_model=0.0,
                                      neighbour_weight=0.0)
    multi = decompose_views(model, views, bgs, V, same, same.grid(data.rig, data.frame_hw))
    single = decompose(model, views, bgs)
    for key in ("windows", "depths", "masks", "raw_masks", "app"):
        assert torch.allclose(getattr(multi, key), getattr(single, key), atol=1e-6), key
    assert multi.slots.shape == (2 * V, model.cfg.num_windows)
    assert single.slots is None
    # the single setting is decompose itself
    one = decompose_views(model, views, bgs, V,
                          InferenceSettings.defaults(views="single", colour_model=0.0,
                                                     neighbour_weight=0.0))
    assert torch.equal(one.masks, single.masks) and one.slots is None
    with pytest.raises(ValueError, match="whole instants"):
        decompose_views(model, views[:3], bgs[:3], V, same, same.grid(data.rig, data.frame_hw))


def test_window_candidates_leave_contested_pixels_to_the_windows_of_nearby_individuals():
    candidates = torch.tensor([[[[1, 1, 0]], [[0, 1, 1]], [[0, 0, 0]]]], dtype=torch.bool)
    contested = candidates.sum(1) >= 2  # (V=1, H=1, W=3): only the middle pixel
    slots = torch.tensor([[2, 0, -1]])  # window 0 holds slot 2, window 1 slot 0, 2 none
    got = window_candidates(candidates, slots, contested)
    # the middle pixel is near slots 0 and 1: of the windows only window 1 (slot 0) may own it
    assert got[0, :, 0, 1].tolist() == [False, True, False]
    assert got[0, :, 0, [0, 2]].all()  # elsewhere every window may


def test_window_owners_map_hull_slots_to_windows():
    owners = torch.tensor([[[0, 1, -1], [1, 1, 0]]])  # (V=1, H=2, W=3) hull slots
    slots = torch.tensor([[1, -1, 0]])  # window 0 holds slot 1, window 2 slot 0
    assert window_owners(owners, slots).tolist() == [[[2, 0, -1], [0, 0, 2]]]


def test_hull_ownership_gives_the_hulls_pixels_to_their_windows(tiny_scene):
    """With a bonus larger than any colour or weight score, every foreground pixel that the
    hull gives to an individual goes to the window fused with that individual."""
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    model = build_model(tiny_cfg().model)
    views, bgs = data.views(0)
    V, k = data.num_views, model.cfg.num_windows
    settings = InferenceSettings.defaults(resolution=16, hull_ownership=1e6, hull_contested=1e6)
    grid = settings.grid(data.rig, data.frame_hw)
    dec = decompose_views(model, views, bgs, V, settings, grid)
    ev = foreground_evidence(views, bgs)
    hull = multiview_proposals(ev, grid, k, split=not model.detector.use_presence)
    win = window_owners(hull.owners, dec.slots)
    held = (win >= 0) & (ev > 0.5)
    assert held.sum() > 0
    got = dec.masks.argmax(1)[held]
    assert torch.equal(got, win[held])
    assert (dec.masks.amax(1)[held] > 0.5).all()


def test_contested_pixels_keep_the_learned_owner(tiny_scene):
    """hull_contested=0 with a huge bonus elsewhere: uncontested pixels go to the hull's
    window, contested ones to the window the learned ownership alone picks."""
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    model = build_model(tiny_cfg().model)
    # instant 0: the two individuals apart (nothing contested); 2: together (all contested)
    views = torch.cat([data.views(t)[0] for t in (0, 2)])
    bgs = torch.cat([data.views(t)[1] for t in (0, 2)])
    V, k = data.num_views, model.cfg.num_windows
    split = not model.detector.use_presence
    mixed = InferenceSettings.defaults(resolution=16, hull_ownership=1e6, hull_contested=0.0)
    learned = InferenceSettings.defaults(resolution=16, hull_ownership=0.0, hull_contested=0.0)
    grid = mixed.grid(data.rig, data.frame_hw)
    dec = decompose_views(model, views, bgs, V, mixed, grid)
    alone = decompose_views(model, views, bgs, V, learned, grid)
    ev = foreground_evidence(views, bgs)
    hulls = [multiview_proposals(ev[s : s + V], grid, k, split=split, contest=CONTEST_BAND)
             for s in (0, V)]
    win = window_owners(torch.cat([h.owners for h in hulls]), dec.slots)
    contested = torch.cat([h.contested for h in hulls])
    fg = ev > 0.5
    sure = (win >= 0) & fg & ~contested
    unsure = fg & contested
    assert sure[:V].sum() > 0 and unsure[V:].sum() > 0
    assert torch.equal(dec.masks.argmax(1)[sure], win[sure])
    per_pixel = dec.masks.permute(0, 2, 3, 1)  # (V, H, W, N)
    assert torch.equal(per_pixel[unsure], alone.masks.permute(0, 2, 3, 1)[unsure])


def test_the_hull_track_carried_alone_is_the_one_decompose_views_carries(tiny_scene):
    """The export's parent carries the hull's track through the instants
    (carry_hull_track) and hands each batch its labels: the track must be the one
    decompose_views reaches through the same instants, and decomposing from the handed
    labels must give what decomposing all the instants in one call gives."""
    data = SceneData(tiny_scene, (32, 24), val_fraction=0.25)
    model = build_model(tiny_cfg().model)
    V = data.num_views
    settings = InferenceSettings.defaults(resolution=16)
    grid = settings.grid(data.rig, data.frame_hw)
    frames = [data.views(t) for t in (0, 1, 2)]
    views, bgs = torch.cat([f[0] for f in frames]), torch.cat([f[1] for f in frames])
    carried, decomposed = ClusterTrack(), ClusterTrack()
    clusters = carry_hull_track(model, views, bgs, V, grid, carried)
    whole = decompose_views(model, views, bgs, V, settings, grid, track=decomposed)
    assert carried.means is not None and len(clusters) == 3
    for name in ("weights", "means", "precisions"):
        assert np.array_equal(getattr(carried, name), getattr(decomposed, name))
    last = decompose_views(model, views[2 * V :], bgs[2 * V :], V, settings, grid,
                           clusters=clusters[2:])
    assert torch.equal(last.slots, whole.slots[2 * V :])
    assert torch.allclose(last.masks, whole.masks[2 * V :])
