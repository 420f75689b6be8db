"""Speckle of the visible masks (nsd/cues/holes.py): holes filled, islands given away."""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.cues.holes import HOLE_SHARE, ISLAND_SHARE, Speckle, fill_holes, give_islands
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


def test_batch_cleans_every_frame_and_keeps_the_dtype():
    rng = np.random.default_rng(1)
    masks = np.zeros((2, 2, 16, 16), bool)
    masks[:, 0, 2:8, 2:8] = True
    masks[:, 1, 9:15, 9:15] = True
    masks &= rng.random(masks.shape) > 0.1
    masks[:, 1, 4, 4] = True  # an island of subject 1 inside subject 0
    masks[:, 0, 4, 4] = False
    t = torch.from_numpy(masks).float()
    rules = Speckle(0.1, 0.05)
    got = rules.clean_batch(t)
    assert got.dtype == torch.float32
    for b in range(2):
        want = fill_holes(give_islands(masks[b], 0.05), 0.1)
        assert np.array_equal(got[b].numpy() > 0.5, want)
        assert want[0, 4, 4] and not want[1, 4, 4]
    assert Speckle(0.0, 0.0).clean_batch(t) is t


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
    assert not native_masks(coarse, view, background, speckle=Speckle(0.0, 0.0))[0][speckle].any()
    assert np.array_equal(native_masks(coarse, view, background)[0], truth)


def test_the_config_holds_the_modules_defaults_and_refuses_bad_shares():
    settings = InferenceSettings.defaults()
    assert settings.speckle == Speckle(HOLE_SHARE, ISLAND_SHARE)
    for key in ("hole_share", "island_share"):
        for bad in (-0.1, 1.5, True, "x"):
            with pytest.raises(ConfigError, match=rf"inference\.{key}"):
                InferenceSettings.defaults(**{key: bad})


def _islands_reference(masks: np.ndarray, share: float) -> np.ndarray:
    """Slowly: every 4-connected piece of every mask found by a flood from each pixel by
    hand; a piece other than its subject's largest (the first of equal largest in scan
    order), no larger than ``share`` of the subject's area, whose 4-neighbours are all
    inside the frame and all of one other subject, goes to that subject."""
    N, H, W = masks.shape
    out = masks.copy()
    for n in range(N):
        seen, pieces = np.zeros((H, W), bool), []
        for y0 in range(H):
            for x0 in range(W):
                if not masks[n, y0, x0] or seen[y0, x0]:
                    continue
                piece, queue = [], deque([(y0, x0)])
                seen[y0, x0] = True
                while queue:
                    y, x = queue.popleft()
                    piece.append((y, x))
                    for v, u in ((y + 1, x), (y - 1, x), (y, x + 1), (y, x - 1)):
                        if 0 <= v < H and 0 <= u < W and masks[n, v, u] and not seen[v, u]:
                            seen[v, u] = True
                            queue.append((v, u))
                pieces.append(piece)
        if len(pieces) < 2:
            continue
        largest = max(range(len(pieces)), key=lambda i: (len(pieces[i]), -i))
        for i, piece in enumerate(pieces):
            if i == largest or len(piece) > share * masks[n].sum():
                continue
            inside = set(piece)
            holders = set()
            for y, x in piece:
                for v, u in ((y + 1, x), (y - 1, x), (y, x + 1), (y, x - 1)):
                    if (v, u) in inside:
                        continue
                    if not (0 <= v < H and 0 <= u < W):
                        holders.add("outside")
                    else:
                        who = np.flatnonzero(masks[:, v, u])
                        holders.add(int(who[0]) if len(who) else "floor")
            if len(holders) == 1 and isinstance(m := holders.pop(), int):
                for y, x in piece:
                    out[n, y, x], out[m, y, x] = False, True
    return out


def test_islands_inside_one_other_subject_are_given_to_it_and_others_stay():
    m = np.zeros((3, 30, 30), bool)
    m[0, 2:26, 2:26] = True  # a big body, 576 pixels
    m[1, 27:29, 2:28] = True  # subject 1's body: 52 pixels, below subject 0 (floor between)
    for y, x in ((5, 5), (10, 10), (24, 12)):  # islands of subject 1: in 0; in 0; ...
        m[1, y, x], m[0, y, x] = True, False
    m[1, 25, 12], m[0, 25, 12] = True, False  # ... (24, 12) with (25, 12) reaches the floor
    m[2, 15:17, 15:17], m[0, 15:17, 15:17] = True, False  # subject 2 alone inside subject 0
    m[1, 15, 17], m[0, 15, 17] = True, False  # an island of 1 between subjects 0 and 2
    got = give_islands(m, 0.02)  # islands of subject 1 up to 1.04 pixels
    assert got[0, 5, 5] and got[0, 10, 10] and not got[1, 5, 5] and not got[1, 10, 10]
    assert got[1, 24, 12] and got[1, 25, 12]  # reaches the floor: stays
    assert got[1, 15, 17]  # two subjects around it: stays
    assert np.array_equal(got[2], m[2])  # a subject's largest piece never moves
    assert not (got.sum(0) > 1).any() and np.array_equal(got.any(0), m.any(0))
    assert np.array_equal(give_islands(m, 0.0), m)  # 0: off
    assert not give_islands(m, 0.01)[0, 5, 5]  # 0.52 pixels: none is small enough


def test_an_island_at_the_frames_edge_stays():
    m = np.zeros((2, 10, 10), bool)
    m[0] = True
    m[0, 0, 4], m[1, 0, 4] = False, True  # subject 1's island on the top edge ...
    m[0, 6:9, 6:9], m[1, 6:9, 6:9] = False, True  # ... beside its largest piece
    got = give_islands(m, 0.5)
    assert np.array_equal(got, m)


def test_islands_match_a_slow_flood_on_random_label_maps():
    rng = np.random.default_rng(3)
    for trial in range(30):
        labels = np.full((20, 20), -1, np.int32)
        for n in range(3):
            c = rng.integers(3, 17, 2)
            cv2.circle(labels, (int(c[0]), int(c[1])), int(rng.integers(3, 7)), n, -1)
        noise = rng.random((20, 20)) < 0.12  # speckle: random pixels of a random subject
        labels[noise] = rng.integers(0, 3, noise.sum())
        masks = labels[None] == np.arange(3)[:, None, None]
        share = float(rng.choice([0.01, 0.03, 0.1]))
        got = give_islands(masks, share)
        assert np.array_equal(got, _islands_reference(masks, share)), trial
        assert np.array_equal(got.any(0), masks.any(0)) and not (got.sum(0) > 1).any()
