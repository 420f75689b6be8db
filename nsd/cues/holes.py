r"""Small holes of the visible masks: where a body's colour is close to the floor behind it.

Every visible mask is drawn from the background residual (:mod:`nsd.cues.evidence`): a
pixel is foreground where the frame differs from the background by more than the cut. Where
a body's colour is close to the floor's behind it (a grey coat on grey bedding, a spotted
coat's light patches) single pixels and small clusters fall below the cut, and the mask
comes out speckled: on a scene of four grey bipeds on a grey floor the masks score mIoU
0.611, 0.639 with their small holes filled (docs/nsd.md, "Speckled masks").

A *hole* of subject :math:`n`'s mask :math:`M_n` is a 4-connected region of pixels outside
:math:`M_n` that :math:`M_n` encloses (it does not reach the frame's border). A hole is given
to :math:`n` when

.. math:: |h| \le s\,|M_n|

and no other subject owns a pixel of it (that subject may be seen there, e.g. a hand in
front of the body), :math:`s` the ``share`` (scale-free: the same rule for a mouse of 100
pixels and a person of 100,000, at any resolution). The masks stay disjoint. Holes that
held a few pixels of another subject were tried too (those pixels moved to :math:`n`):
masks up to 0.011 better in mIoU, but detection up to 0.012 worse on 4 runs, since a
front subject's fragments over a body are taken from it (docs/nsd.md, "Speckled masks").
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor

__all__ = ["HOLE_SHARE", "fill_holes", "fill_holes_batch"]

# The largest hole filled, as a share of its subject's visible area. conf/inference/default.yaml
# (``inference.hole_share``) holds the same value; chosen on 16 runs (docs/benchmarks/holes.md:
# 0.02, 0.04 and 0.08 within 0.002 of each other in mask mIoU, detection unchanged).
HOLE_SHARE = 0.04


def fill_holes(masks: np.ndarray, share: float = HOLE_SHARE) -> np.ndarray:
    """Fill the small holes of disjoint visible masks (module docstring).

    Args:
        masks: (N, H, W) bool, disjoint.
        share: largest hole filled, as a share of its subject's area (0: none).

    Returns:
        (N, H, W) bool, disjoint; a new array.
    """
    out = np.array(masks, dtype=bool, copy=True)
    if share <= 0 or out.size == 0:
        return out
    N = out.shape[0]
    union = out.any(0)
    for n in range(N):
        limit = share * out[n].sum()
        if limit < 1:
            continue
        count, labels, stats, _ = cv2.connectedComponentsWithStats(
            (~out[n]).astype(np.uint8), connectivity=4)
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        small = stats[:, cv2.CC_STAT_AREA] <= limit
        small[border] = False
        small[0] = False  # label 0: the mask itself
        if not small.any():
            continue
        others = union & ~out[n]  # a hole where another subject shows stays open
        small &= np.bincount(labels[others], minlength=count) == 0
        hole = small[labels]
        if not hole.any():
            continue
        out[n, hole] = True
        union |= hole
    return out


def fill_holes_batch(masks: Tensor, share: float = HOLE_SHARE) -> Tensor:
    """:func:`fill_holes` for each frame of (B, N, H, W) disjoint 0/1 masks (any dtype);
    returns them in the same dtype."""
    if share <= 0 or masks.numel() == 0:
        return masks
    binary = (masks > 0.5).cpu().numpy()
    filled = np.stack([fill_holes(frame, share) for frame in binary])
    return torch.from_numpy(filled).to(device=masks.device, dtype=masks.dtype)
