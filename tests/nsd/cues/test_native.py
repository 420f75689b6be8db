"""Visible masks at native resolution (nsd/cues/native.py)."""

from __future__ import annotations

import cv2
import numpy as np

from nsd.cues.native import native_masks
from nsd.io.coco_results import resize_mask


def _scene(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two subjects at ``size`` x ``size``: a disc and a bar with a thin diagonal limb; the
    frame (RGB uint8), its background and the true masks (2, size, size)."""
    s = size / 64
    truth = np.zeros((2, size, size), np.uint8)
    cv2.circle(truth[0], (int(18 * s), int(30 * s)), int(10 * s), 1, -1)
    cv2.rectangle(truth[1], (int(38 * s), int(14 * s)), (int(50 * s), int(50 * s)), 1, -1)
    cv2.line(truth[1], (int(50 * s), int(20 * s)), (int(62 * s), int(4 * s)), 1,
             max(1, int(1.5 * s)))
    background = np.full((size, size, 3), 60, np.uint8)
    view = background.copy()
    view[truth[0] > 0] = (200, 40, 40)
    view[truth[1] > 0] = (40, 200, 60)
    return view, background, truth.astype(bool)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_equal_resolution_gives_back_the_masks():
    view, background, truth = _scene(64)
    got = native_masks(truth.astype(np.float32), view, background)
    assert np.array_equal(got, truth)


def test_native_masks_recover_what_upsampling_loses():
    """Masks decided at 16 x 16, frames at 128 x 128: the native masks follow the true
    boundaries and the thin limb; upsampled training-size masks do not."""
    view, background, truth = _scene(128)
    low = np.stack([cv2.resize(t.astype(np.float32), (16, 16), interpolation=cv2.INTER_AREA)
                    for t in truth]) > 0.5
    got = native_masks(low.astype(np.float32), view, background)
    upsampled = np.stack([resize_mask(m.astype(np.float32), (128, 128)) > 0.5 for m in low])
    for k in range(2):
        assert _iou(got[k], truth[k]) > 0.97
        assert _iou(got[k], truth[k]) > _iou(upsampled[k], truth[k]) + 0.05
    assert not (got[0] & got[1]).any()  # disjoint
    assert native_masks(np.zeros((0, 16, 16), np.float32), view, background).shape == (
        0, 128, 128)


def _touching(colours: tuple[tuple[int, int, int], tuple[int, int, int]]):
    """Two subjects side by side at 128 x 128 meeting at x = 64, and masks decided at
    16 x 16 that place the meeting 16 native pixels too far right (x = 80)."""
    truth = np.zeros((2, 128, 128), bool)
    truth[0, 30:90, 20:64] = True
    truth[1, 30:90, 64:108] = True
    background = np.full((128, 128, 3), 60, np.uint8)
    view = background.copy()
    for k in range(2):
        view[truth[k]] = colours[k]
    coarse = np.zeros((2, 16, 16), np.float32)
    coarse[0, 4:11, 2:10] = 1  # x 16..80 at 8 native pixels a cell
    coarse[1, 4:11, 10:14] = 1  # x 80..112
    return view, background, truth, coarse


def test_colour_moves_the_boundary_between_touching_subjects_to_where_colours_meet():
    view, background, truth, coarse = _touching(((200, 40, 40), (40, 200, 60)))
    got = native_masks(coarse, view, background)
    for k in range(2):
        assert _iou(got[k], truth[k]) > 0.97, k
    assert not (got[0] & got[1]).any()


def test_look_alike_subjects_keep_the_spatial_boundary():
    """Same colours: no colour tells them apart, the coarse masks' boundary stays
    (within the blur), so the second subject loses the 16 pixels the coarse masks gave away."""
    view, background, truth, coarse = _touching(((200, 40, 40), (200, 40, 40)))
    got = native_masks(coarse, view, background)
    assert (got[0] | got[1]).sum() == (truth[0] | truth[1]).sum()  # the foreground is right
    assert 0.55 < _iou(got[1], truth[1]) < 0.75
    assert got[0][:, 70:76].all(axis=1)[30:90].all()  # x 70..75 still the first subject's


def test_colour_owners_needs_a_core_for_every_subject():
    """A subject without MIN_CORE core pixels: the spatial owners are returned unchanged."""
    from nsd.cues.native import colour_owners

    view, _, _, _ = _touching(((200, 40, 40), (40, 200, 60)))
    prior = np.zeros((2, 128, 128), np.float32)
    prior[0, 30:90, 20:100] = 1.0
    prior[1, 60:64, 100:108] = 1.0  # 32 pixels
    owner = prior.argmax(0)
    claimed = prior.max(0) > 0
    assert np.array_equal(colour_owners(view, prior, owner, claimed), owner)


def test_a_patch_of_a_neighbours_colour_inside_a_body_stays_with_that_body():
    """The second subject wears a patch of the first's colour in the middle of its body, 20
    native pixels from where they meet: colour alone would give the patch to the first
    subject; detached from its spatial share, it stays with the second, while the boundary
    still moves to where the colours meet."""
    view, background, truth, coarse = _touching(((200, 40, 40), (40, 200, 60)))
    view[50:60, 88:96] = (200, 40, 40)  # the patch, inside the second subject's body
    got = native_masks(coarse, view, background)
    assert got[1][50:60, 88:96].all() and not got[0][50:60, 88:96].any()
    assert _iou(got[0], truth[0]) > 0.97  # the boundary moved as before
    from nsd.cues.native import anchored_owners, colour_owners

    prior = np.stack([cv2.GaussianBlur(cv2.resize(c, (128, 128)), (0, 0), 8) for c in coarse])
    spatial, claimed = prior.argmax(0), (truth[0] | truth[1])
    by_colour = colour_owners(view, prior, spatial, claimed)
    assert (by_colour[50:60, 88:96] == 0).all()  # what anchoring undoes
    assert (anchored_owners(by_colour, spatial, claimed, 2)[50:60, 88:96] == 1).all()
