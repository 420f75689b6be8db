r"""Speckle of the visible masks: small holes filled, small islands given away.

Every visible mask is drawn from the background residual (:mod:`nsd.cues.evidence`) and
its pixels go to the subject that owns them (:mod:`nsd.inference.single`). Both leave
speckle, which :class:`Speckle` cleans in two rules (docs/nsd.md, "Speckled masks").

*Holes.* Where a body's colour is close to the floor's behind it (a grey coat on grey
bedding, a spotted coat's light patches) single pixels and small clusters fall below the
residual's cut: on a scene of four grey bipeds on a grey floor the masks score mIoU 0.611,
0.639 with their small holes filled. A *hole* of subject :math:`n`'s mask :math:`M_n` is a
4-connected region of pixels outside :math:`M_n` that :math:`M_n` encloses (it does not
reach the frame's border). A hole is given to :math:`n` when

.. math:: |h| \le s_h\,|M_n|

and no other subject owns a pixel of it (that subject may be seen there, e.g. a hand in
front of the body), :math:`s_h` the ``hole_share``. Holes that held a few pixels of another
subject were tried too (those pixels moved to :math:`n`): masks up to 0.011 better in
mIoU, but detection up to 0.012 worse on 4 runs, since a front subject's fragments over a
body are taken from it.

*Islands.* Where two textured bodies touch, single pixels of one whose colour the other's
coat also has go to the other (the individuals' colour models, the learned weights): the
front body comes out sprinkled with the other's pixels. An *island* of :math:`n` is a
4-connected component of :math:`M_n` other than its largest, with

.. math:: |c| \le s_i\,|M_n|,

whose 4-neighbours all belong to one other subject :math:`m` (none on the floor, none
outside the frame); it is given to :math:`m`. A fragment that reaches the floor or a third
subject (a hand held out over another body's outline) stays. Both shares are of the mask's
own area: the same rules for a mouse of 100 pixels and a person of 100,000, at any
resolution. The masks stay disjoint and their union does not change.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

__all__ = ["HOLE_SHARE", "ISLAND_SHARE", "SPECKLE", "Speckle", "fill_holes", "give_islands"]

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


# The largest island given away, as a share of its subject's visible area;
# conf/inference/default.yaml (``inference.island_share``) holds the same value. Chosen on 6
# runs (docs/benchmarks/islands.md): 0.01 and 0.04 within 0.003 of each other in mask mIoU,
# 0.04 the higher on all 6 and the share the holes use.
ISLAND_SHARE = 0.04


def give_islands(masks: np.ndarray, share: float = ISLAND_SHARE) -> np.ndarray:
    """Give each small island of a subject's mask to the one subject around it (module
    docstring).

    Args:
        masks: (N, H, W) bool, disjoint.
        share: largest island moved, as a share of its subject's area (0: none).

    Returns:
        (N, H, W) bool, disjoint, the same union; a new array.
    """
    out = np.array(masks, dtype=bool, copy=True)
    if share <= 0 or out.shape[0] < 2 or out.size == 0:
        return out
    N = out.shape[0]
    beyond = None  # every pixel's owner, -1 on the floor, -2 outside the frame: when needed
    moves = []
    for n in range(N):
        limit = share * out[n].sum()
        if limit < 1:
            continue
        count, labels, stats, _ = cv2.connectedComponentsWithStats(
            out[n].astype(np.uint8), connectivity=4)
        area = stats[:, cv2.CC_STAT_AREA]
        small = area <= limit
        small[0] = False  # label 0: the rest of the frame
        small[1 + int(area[1:].argmax()) if count > 1 else 0] = False  # its largest piece
        if not small.any():
            continue
        if beyond is None:
            owner = np.where(out.any(0), out.argmax(0), -1)
            beyond = np.pad(owner, 1, constant_values=-2)
        # which owners each small piece's 4-neighbours have (columns: outside the frame, the
        # floor, subject 0, 1, ...); a neighbour of n's own lies in the same piece
        ys, xs = np.nonzero(small[labels])
        piece = labels[ys, xs]
        seen = np.zeros((count, N + 2), bool)
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            nb = beyond[ys + 1 + dy, xs + 1 + dx]
            other = nb != n
            seen[piece[other], nb[other] + 2] = True
        given = small & (seen.sum(1) == 1) & ~seen[:, :2].any(1)
        move = given[piece]
        if move.any():
            moves.append((n, ys[move], xs[move], seen[piece[move], 2:].argmax(1)))
    for n, ys, xs, holder in moves:
        out[n, ys, xs] = False
        out[holder, ys, xs] = True
    return out


@dataclass(frozen=True)
class Speckle:
    """The two speckle rules of the visible masks (module docstring); a share of 0 turns
    its rule off."""

    hole_share: float = HOLE_SHARE
    island_share: float = ISLAND_SHARE

    def clean(self, masks: np.ndarray) -> np.ndarray:
        """(N, H, W) disjoint bool masks with their islands given away, then their holes
        filled; a new array."""
        return fill_holes(give_islands(masks, self.island_share), self.hole_share)

    def clean_batch(self, masks: Tensor) -> Tensor:
        """:meth:`clean` for each frame of (B, N, H, W) disjoint 0/1 masks (any dtype);
        returns them in the same dtype."""
        if (self.hole_share <= 0 and self.island_share <= 0) or masks.numel() == 0:
            return masks
        binary = (masks > 0.5).cpu().numpy()
        clean = np.stack([self.clean(frame) for frame in binary])
        return torch.from_numpy(clean).to(device=masks.device, dtype=masks.dtype)


SPECKLE = Speckle()  # the shipped rules
