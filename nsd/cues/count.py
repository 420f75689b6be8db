"""How many separate bodies the visual hull of a scene shows: a lower bound on its
individuals, label-free, to check ``model.num_windows`` against before training.

Per instant, the occupied voxels (:func:`nsd.cues.occupancy.occupied_voxels`) are counted
per column of the horizontal plane, and the columns of at least ``MIN_COLUMN`` voxels are
joined into *blobs* across gaps of up to ``2 * BLOB_GAP`` empty columns, as the hull's
clustering joins the pieces one carved body falls into (:mod:`nsd.cues.clustering`). A blob
is a *body* when

* its fullest column holds at least ``BODY_SHARE`` times the scene's typical fullest column
  (the median over the instants of each instant's fullest): ghosts of the hull are low,
  bodies tall, whatever the species' volume (a biped's blob holds a tenth of a cow's voxels,
  its fullest column as many), and
* its top lies at most ``TOP_DROP`` typical fullest columns below the scene's typical top
  (the median of the instants' highest voxels): the cone a body carves below the floor,
  where the working volume reaches under it, is a blob as full as a body but low.

Bodies that touch are one blob, so an instant undercounts where bodies touch; the scene's
count is the ``QUANTILE`` of the instants' counts, the most the hull shows in more than a
tenth of them. Footage of fewer than ``MIN_FRAMES`` frames or ``MIN_VIEWS`` cameras is not counted.

Measured on 24 synthetic scenes of 1-8 individuals, 4-8 cameras
(docs/benchmarks/hull_count.md; the rule chosen on 20 of them): the right count on 21, fewer
on three (three cows of one texture huddling most of the time: 2; five individuals of whom
one lingers in the background: 4; eight walking freely on 8 cameras: 5), never more; without
the top's test three scenes of 5 and 6 cameras count one or two more. At 64 x 64 pixels the
hull's pieces can count one more.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from nsd.cameras.calibration import CameraRig
from nsd.cues.clustering import BLOB_GAP, MIN_COLUMN
from nsd.cues.occupancy import VoxelGrid, occupied_voxels, voxel_grid
from nsd.ops.vectors import up_frame

__all__ = ["BODY_SHARE", "MIN_FRAMES", "MIN_VIEWS", "QUANTILE", "SAMPLE", "TOP_DROP", "blobs",
           "body_counts", "countable", "footage_bodies", "sampled_frames", "scene_bodies"]

BODY_SHARE = 0.4  # a blob's fullest column against the scene's typical one (0.5: 19 of 24)
TOP_DROP = 0.5  # typical fullest columns a body's top may lie below the typical top (0.3-0.7)
QUANTILE = 0.9  # of the instants' counts (0.75 undercounts huddles: 10 of the first 20)
# shorter footage is not counted: its background holds its subjects and the hull falls into
# pieces (80-frame scenes at 64 x 64: two individuals counted as three)
MIN_FRAMES = 60
# nor footage of fewer cameras: two or three views carve full-height ghosts where their
# cones of two bodies cross (measured on 4-8 cameras only)
MIN_VIEWS = 4
SAMPLE = 60  # frames spread over the footage in which the bodies are counted


def countable(frames: int, views: int) -> bool:
    """Footage of ``frames`` frames and ``views`` cameras is long and wide enough to count.

        >>> countable(300, 4), countable(59, 8), countable(300, 3)
        (True, False, False)
    """
    return frames >= MIN_FRAMES and views >= MIN_VIEWS


def sampled_frames(frames: int, sample: int = SAMPLE) -> np.ndarray:
    """``sample`` frame indices spread evenly over ``frames`` (all of them if fewer).

        >>> sampled_frames(5, 3).tolist(), sampled_frames(2).tolist()
        ([0, 2, 4], [0, 1])
    """
    return np.unique(np.linspace(0, frames - 1, min(sample, frames)).round().astype(int))


def blobs(points: Tensor, up: Tensor, cell: float) -> np.ndarray:
    """The blobs of one instant's occupied voxel centres (P, 3), module docstring: (B, 2)
    float, each blob's fullest column (voxels) and its top (height along ``up``), fullest
    first; (0, 2) without any column of ``MIN_COLUMN`` voxels.

        >>> up = torch.tensor([0.0, 0.0, 1.0])
        >>> tall = torch.tensor([[0.5, 0.5, z + 0.5] for z in range(6)])  # 6 voxels high
        >>> low = torch.tensor([[9.5, 0.5, 0.5], [9.5, 0.5, 1.5]])  # 2 high, 9 columns away
        >>> blobs(torch.cat([tall, low]), up, 1.0).tolist()
        [[6.0, 5.5], [2.0, 1.5]]
    """
    if len(points) == 0:
        return np.zeros((0, 2))
    p = (points @ up_frame(up)).numpy()
    ij = np.floor((p[:, :2] - p[:, :2].min(0)) / cell).astype(np.int64)
    counts = np.zeros(tuple(ij.max(0) + 1))
    np.add.at(counts, (ij[:, 0], ij[:, 1]), 1)
    top = np.full(counts.shape, -np.inf)
    np.maximum.at(top, (ij[:, 0], ij[:, 1]), p[:, 2])
    kept = counts >= MIN_COLUMN
    joined = ndimage.binary_dilation(kept, iterations=BLOB_GAP) if BLOB_GAP else kept
    labels, n = ndimage.label(joined)
    if n == 0:
        return np.zeros((0, 2))
    index = np.arange(1, n + 1)
    out = np.stack([np.asarray(ndimage.maximum(np.where(kept, counts, 0), labels, index)),
                    np.asarray(ndimage.maximum(np.where(kept, top, -np.inf), labels, index))],
                   1).astype(float)
    return out[np.argsort(-out[:, 0], kind="stable")]


def body_counts(instants: list[np.ndarray], cell: float) -> np.ndarray:
    """Bodies per instant (T,) int from each instant's :func:`blobs` (``cell``: the voxel
    side), by the module docstring's two tests.

        >>> body = np.array([[10.0, 2.0]])
        >>> ghost, cone = np.array([[2.0, 2.0]]), np.array([[10.0, -1.0]])
        >>> body_counts([np.concatenate([body, body, ghost, cone]), body, np.zeros((0, 2))],
        ...             cell=0.1).tolist()
        [2, 1, 0]
    """
    seen = [b for b in instants if len(b)]
    if not seen:
        return np.zeros(len(instants), int)
    column = float(np.median([b[:, 0].max() for b in seen]))
    top = float(np.median([b[:, 1].max() for b in seen]))
    return np.array([int(((b[:, 0] >= BODY_SHARE * column)
                          & (b[:, 1] >= top - TOP_DROP * column * cell)).sum())
                     for b in instants])


def scene_bodies(evidence: Callable[[int], Tensor], instants: Iterable[int],
                 grid: VoxelGrid) -> tuple[int, np.ndarray]:
    """The bodies the hull shows in a scene: (count, per-instant counts (T,)), the count the
    ``QUANTILE`` of the per-instant counts (a lower bound on the individuals; 0 without any
    instant).

    Args:
        evidence: instant -> (V, H, W) foreground evidence.
        instants: the instants to look at (e.g. a few dozen spread over the footage).
        grid: the scene's voxel grid.
    """
    found = []
    for t in instants:
        idx = torch.nonzero(occupied_voxels(evidence(t), grid)).flatten()
        found.append(blobs(grid.centres[idx], grid.up, grid.size))
    counts = body_counts(found, grid.size)
    if len(counts) == 0:
        return 0, counts
    return int(np.quantile(counts, QUANTILE, method="lower")), counts


def footage_bodies(evidence: Callable[[int], Tensor], frames: int, rig: CameraRig,
                   frame_hw: tuple[int, int], resolution: int, min_views: int | str = "auto"
                   ) -> tuple[int, np.ndarray]:
    """:func:`scene_bodies` of :data:`SAMPLE` frames spread over footage of ``frames`` frames,
    in the voxel grid of ``resolution`` voxels per side and ``min_views`` that the hull's
    proposals use (``prior_proposal.resolution``, ``prior_proposal.min_views``).

    Args:
        evidence: frame -> (V, H, W) foreground evidence at ``frame_hw`` (H, W).
    """
    grid = voxel_grid(rig, frame_hw, resolution, min_views=min_views,
                      key="prior_proposal.min_views")
    return scene_bodies(evidence, sampled_frames(frames), grid)
