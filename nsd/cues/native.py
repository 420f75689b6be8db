r"""Visible masks at the footage's own resolution, from masks decided at the training size.

NSD decides who is where at the training resolution (128 x 128 by default); a 1280 x 1024
camera then gets a mask 10 times coarser than its pixels if the masks are only upsampled.
The refinement at the training size (:mod:`nsd.inference.single`, ``refine="residual"``)
already draws each mask from the background residual, the foreground pixels going to the
subject that owns them; this module applies the same rule at native resolution:

* ownership: each subject's training-size mask upsampled (bilinear) and blurred by a
  Gaussian of one training pixel (:math:`\sigma = s`, the scale factor), so that a native
  pixel just outside a coarse mask still has an owner; a pixel goes to the subject with
  the largest value there;
* reach: pixels within :math:`\lceil 2 s \rceil` native pixels of any upsampled mask
  (a thin limb the coarse mask missed by a pixel is found; the rest of the frame is not
  searched);
* foreground: the background residual of the native frame against the native background
  (:func:`nsd.cues.evidence.foreground_evidence` above 0.5, the cut used everywhere).

* colour: with two or more subjects, the spatial owner is only a prior. Each subject's
  colours are counted in its *core* (foreground pixels it owns with a prior above
  ``CORE_PRIOR`` where no other subject's prior reaches ``CORE_OTHERS``; a histogram of
  ``COLOUR_LEVELS``\ :sup:`3` bins, with ``COLOUR_PSEUDO`` of its count spread evenly over
  the bins, so that an unseen colour is as unlikely for a small subject as for a large
  one), and every claimed pixel goes to the subject maximising

  .. math:: \log p_n(c) + \beta \log(o_n + \epsilon),

  :math:`p_n` the subject's colour histogram, :math:`o_n` its blurred upsampled mask,
  :math:`\beta` = ``PRIOR_WEIGHT``. Where the subjects' colours are alike the prior
  decides; where they differ, colour moves the boundary between touching subjects to
  where their clothes or coats meet, which a mask decided 10 times coarser cannot place.
  Without ``MIN_CORE`` core pixels for every subject, the prior alone decides.
* anchoring: colour moves a region of pixels to subject :math:`n` only where the region
  holds on to :math:`n`'s spatial share (a region of 8-connected pixels colour gives
  :math:`n` that contains a pixel the spatial owner gives :math:`n` too,
  :func:`anchored_owners`); detached pieces go back to the spatial owner. A boundary moves,
  a body's colour sprinkled over its neighbours' does not: five individuals of similar
  coats at 160 x 120 came out speckled across the whole frame, each subject's box the
  frame's (mIoU 0.49, against 0.66 with the spatial owner alone), 0.66 anchored.

A subject's native mask is the foreground pixels within reach that it owns, its speckle
cleaned as at the training size (:mod:`nsd.cues.holes`: small holes filled, small islands
given to the subject around them). At equal
resolution it gives back the training-size masks up to pixels at their boundaries.

Measured on a 1280 x 1024 synthetic scene (docs/benchmarks/native_hd.md): mIoU 0.65
upsampled, 0.74 with the spatial owner alone, 0.85 with colour; the union of the masks
scores 0.95 against the truth, so who owns a pixel, not where the foreground is, is what
remains. Anchoring (docs/scaling.md, "Colour that holds on to the subject"), on five
scenes: +0.02 to +0.17 on three crowded ones, -0.003 and -0.017 on two clean ones where
colour had rightly moved a detached limb.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from nsd.cues.colour_cells import colour_cells
from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD, foreground_evidence
from nsd.cues.holes import SPECKLE, Speckle

__all__ = ["anchored_owners", "colour_owners", "native_masks"]

COLOUR_LEVELS = 16  # per channel: the colour histograms have 16^3 bins
PRIOR_WEIGHT = 0.1  # beta: weight of the spatial prior's log against the colour's
OWNER_FLOOR = 1e-3  # epsilon: the prior's floor (a pixel outside a subject's blurred mask)
CORE_PRIOR = 0.5  # a core pixel: its subject's prior above this ...
CORE_OTHERS = 0.05  # ... and every other subject's below this
MIN_CORE = 50  # core pixels every subject needs for colour ownership
COLOUR_PSEUDO = 0.01  # a histogram's added counts, spread over its bins, as a share of its core


def native_masks(
    masks: np.ndarray,
    view: np.ndarray,
    background: np.ndarray,
    evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS,
    colour: bool = True,
    speckle: Speckle = SPECKLE,
) -> np.ndarray:
    """Native-resolution visible masks (module docstring).

    Args:
        masks: training-size visible masks of the frame's subjects, (N, h, w) in [0, 1].
        view: the native frame, (H, W, 3) uint8 RGB.
        background: its native background, (H, W, 3) uint8 RGB.
        colour: the subjects' colours move the boundaries between them (false: the
            spatial owner alone).
        speckle: the masks' small holes filled and small islands given to the subject
            around them, as at the training size (:class:`nsd.cues.holes.Speckle`).

    Returns:
        (N, H, W) bool, disjoint.
    """
    N, h, w = masks.shape
    H, W = view.shape[:2]
    if N == 0:
        return np.zeros((0, H, W), bool)
    scale = max(H / h, W / w)
    up = np.stack([cv2.resize(m.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
                   for m in masks])
    sigma = max(scale, 0.5)
    owners = np.stack([cv2.GaussianBlur(u, (0, 0), sigma) for u in up])
    radius = math.ceil(2 * scale)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    reach = cv2.dilate((up.max(0) > 0).astype(np.uint8), kernel) > 0
    to_t = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float().div_(255.0)  # noqa: E731
    fg = foreground_evidence(to_t(view), to_t(background), evidence_threshold,
                             evidence_softness)[0].numpy() > 0.5
    owner = owners.argmax(0)
    claimed = reach & fg & (owners.max(0) > 0)
    if colour and N >= 2:
        owner = anchored_owners(colour_owners(view, owners, owner, claimed), owner, claimed, N)
    return speckle.clean((owner[None] == np.arange(N)[:, None, None]) & claimed[None])


def anchored_owners(colour: np.ndarray, spatial: np.ndarray, claimed: np.ndarray,
                    N: int) -> np.ndarray:
    """The colour's owners where they hold on to the spatial owner's (module docstring): a
    region colour gives subject :math:`n` (8-connected claimed pixels of :math:`n`) keeps it
    when it holds a pixel the spatial owner gives :math:`n` too; elsewhere the spatial owner.

    Args:
        colour: (H, W) int, :func:`colour_owners`' result.
        spatial: (H, W) int, the blurred upsampled masks' argmax.
        claimed: (H, W) bool, the pixels assigned.
        N: the number of subjects.

    Returns:
        (H, W) int, a new array.

        >>> spatial = np.array([[0, 0, 1, 1, 1, 1]])
        >>> colour = np.array([[0, 0, 0, 1, 0, 1]])  # a sliver of 0 joined to it, an island
        >>> anchored_owners(colour, spatial, np.ones((1, 6), bool), 2).tolist()
        [[0, 0, 0, 1, 1, 1]]
    """
    out = colour.copy()
    for n in range(N):
        mine = claimed & (colour == n)
        count, labels = cv2.connectedComponents(mine.astype(np.uint8), connectivity=8)
        held = np.bincount(labels[mine & (spatial == n)], minlength=count) > 0
        held[0] = True  # label 0: not n's
        back = ~held[labels]
        out[back] = spatial[back]
    return out


def colour_owners(view: np.ndarray, prior: np.ndarray, owner: np.ndarray,
                  claimed: np.ndarray) -> np.ndarray:
    """Each claimed pixel's subject by its colour and the spatial prior (module docstring).

    Args:
        view: (H, W, 3) uint8.
        prior: (N, H, W) float, each subject's blurred upsampled mask in [0, 1].
        owner: (H, W) int, the prior's argmax.
        claimed: (H, W) bool, the pixels to assign.

    Returns:
        (H, W) int: ``owner`` with the claimed pixels re-assigned (unchanged where some
        subject has fewer than ``MIN_CORE`` core pixels).
    """
    N = len(prior)
    code = colour_cells(torch.from_numpy(view).permute(2, 0, 1).float() / 255.0,
                        COLOUR_LEVELS).numpy()
    bins = COLOUR_LEVELS**3
    pixels = code[claimed]
    score = PRIOR_WEIGHT * np.log(prior[:, claimed] + OWNER_FLOOR)  # (N, K)
    for n in range(N):
        others = np.delete(prior, n, 0).max(0)
        core = claimed & (owner == n) & (prior[n] > CORE_PRIOR) & (others < CORE_OTHERS)
        if core.sum() < MIN_CORE:
            return owner
        hist = np.bincount(code[core], minlength=bins).astype(np.float64)
        hist += COLOUR_PSEUDO * hist.sum() / bins  # the same share for every subject
        score[n] += np.log(hist / hist.sum())[pixels]
    out = owner.copy()
    out[claimed] = score.argmax(0)
    return out
