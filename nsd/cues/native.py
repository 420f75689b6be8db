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

A subject's native mask is the foreground pixels within reach that it owns. At equal
resolution it gives back the training-size masks up to pixels at their boundaries.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from nsd.cues.evidence import EVIDENCE_SOFTNESS, EVIDENCE_THRESHOLD, foreground_evidence

__all__ = ["native_masks"]


def native_masks(
    masks: np.ndarray,
    view: np.ndarray,
    background: np.ndarray,
    evidence_threshold: float = EVIDENCE_THRESHOLD,
    evidence_softness: float = EVIDENCE_SOFTNESS,
) -> np.ndarray:
    """Native-resolution visible masks (module docstring).

    Args:
        masks: training-size visible masks of the frame's subjects, (N, h, w) in [0, 1].
        view: the native frame, (H, W, 3) uint8 RGB.
        background: its native background, (H, W, 3) uint8 RGB.

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
    return (owner[None] == np.arange(N)[:, None, None]) & claimed[None]
