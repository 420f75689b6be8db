"""Small holes of the visible masks (nsd/cues/holes.py)."""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.cues.holes import HOLE_SHARE, fill_holes, fill_holes_batch
from nsd.cues.native import native_masks
from nsd.inference.multiview import InferenceSettings


def _reference(mask: np.ndarray, share: float) -> np.ndarray:
    """One subject, slowly: flood every 4-connected region outside the mask from a seed
    pixel by hand; a region that never reaches the border and is no larger than
    ``share`` of the mask's area is filled."""
    H, W = mask.shape
    out, seen, limit = mask.copy(), mask.copy(), share * mask.sum()
    for y0 in range(H):
        for x0 in range(W):
            if seen[y0, x0]:
                continue
            region, border, queue = [], False, deque([(y0, x0)])
            seen[y0, x0] = True
            while queue:
                y, x = queue.popleft()
                region.append((y, x))
                border |= y in (0, H - 1) or x in (0, W - 1)
                for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                    v, u = y + dy, x + dx
                    if 0 <= v < H and 0 <= u < W and not seen[v, u]:
                        seen[v, u] = True
                        queue.append((v, u))
            if not border and len(region) <= limit:
                for y, x in region:
                    out[y, x] = True
    return out


def test_holes_up_to_the_share_of_the_area_are_filled_and_larger_ones_kept():
    m = np.zeros((1, 20, 20), bool)
    m[0, 2:18, 2:18] = True  # 256 pixels
    m[0, 5, 5] = False  # a speckle: 1 pixel
    m[0, 10:13, 10:13] = False  # a 9-pixel hole
    area = m.sum()  # 246
    filled = fill_holes(m, 4 / area)  # holes up to 4 pixels
    assert filled[0, 5, 5] and not filled[0, 10:13, 10:13].any()
    assert filled.sum() == area + 1
    assert fill_holes(m, 9 / area)[0, 2:18, 2:18].all()  # both filled
    assert np.array_equal(fill_holes(m, 0.0), m)  # 0: off


def test_a_notch_open_to_the_border_and_diagonal_gaps_are_not_holes():
    m = np.zeros((1, 12, 12), bool)
    m[0, 0:8, 0:8] = True
    m[0, 0:3, 3] = False  # a notch from the frame's top edge
    m[0, 7, 7] = False  # the mask's corner pixel: open to the outside
    filled = fill_holes(m, 0.5)
    assert np.array_equal(filled, m)
    ring = np.zeros((1, 7, 7), bool)  # a pixel enclosed by 4-neighbours only diagonally open
    ring[0, 1:6, 1:6] = True
    ring[0, 3, 3] = False
    ring[0, 2, 2] = False  # touches (3, 3) at a corner: two separate 4-connected holes
    assert fill_holes(ring, 0.1)[0, 1:6, 1:6].all()


def test_matches_a_slow_flood_fill_on_random_masks():
    rng = np.random.default_rng(0)
    for trial in range(20):
        blob = np.zeros((24, 24), np.uint8)
        for _ in range(3):
            c = rng.integers(4, 20, 2)
            cv2.circle(blob, (int(c[0]), int(c[1])), int(rng.integers(3, 8)), 1, -1)
        speckled = (blob > 0) & (rng.random((24, 24)) > 0.15)
        share = float(rng.choice([0.005, 0.02, 0.05]))
        got = fill_holes(speckled[None], share)[0]
        assert np.array_equal(got, _reference(speckled, share)), trial


def test_a_hole_where_another_subject_shows_stays_open():
    m = np.zeros((3, 30, 30), bool)
    m[0, 2:28, 2:28] = True
    m[0, 12:15, 12:15] = False  # subject 1 lies wholly inside subject 0's outline
    m[1, 12:15, 12:15] = True
    m[0, 5:7, 20] = False  # a 2-pixel hole holding one pixel of subject 2 ...
    m[2, 5, 20] = True
    m[2, 0:2, 0:10] = True  # ... whose 20 other pixels lie outside subject 0
    m[0, 20, 5] = False  # an empty 1-pixel hole
    got = fill_holes(m, 0.05)
    assert not (got.sum(0) > 1).any()  # disjoint
    assert np.array_equal(got[1], m[1]) and np.array_equal(got[2], m[2])
    assert not got[0, 5:7, 20].any()  # the hole that shows subject 2 stays open
    assert np.array_equal(got[0], m[0] | (np.arange(30)[:, None] == 20)
                          & (np.arange(30)[None] == 5))  # only the empty hole is filled


def test_batch_fills_every_frame_and_keeps_the_dtype():
    rng = np.random.default_rng(1)
    masks = np.zeros((2, 2, 16, 16), bool)
    masks[:, 0, 2:8, 2:8] = True
    masks[:, 1, 9:15, 9:15] = True
    masks &= rng.random(masks.shape) > 0.1
    t = torch.from_numpy(masks).float()
    got = fill_holes_batch(t, 0.1)
    assert got.dtype == torch.float32
    for b in range(2):
        assert np.array_equal(got[b].numpy() > 0.5, fill_holes(masks[b], 0.1))
    assert fill_holes_batch(t, 0.0) is t


def test_native_masks_fill_the_speckle_of_a_body_close_to_the_floors_colour():
    truth = np.zeros((64, 64), bool)
    truth[10:50, 20:40] = True
    background = np.full((64, 64, 3), 100, np.uint8)
    view = background.copy()
    view[truth] = 180
    speckle = np.zeros_like(truth)
    speckle[20:40:4, 24:36:4] = True  # pixels of the body that match the floor
    view[speckle] = 101
    coarse = truth[None].astype(np.float32)
    assert not native_masks(coarse, view, background, hole_share=0.0)[0][speckle].any()
    assert np.array_equal(native_masks(coarse, view, background)[0], truth)


def test_the_config_holds_the_modules_default_and_refuses_bad_shares():
    assert InferenceSettings.defaults().hole_share == HOLE_SHARE
    for bad in (-0.1, 1.5, True, "x"):
        with pytest.raises(ConfigError, match=r"inference\.hole_share"):
            InferenceSettings.defaults(hole_share=bad)
