r"""Multi-view occupancy from background residuals: label-free 3D proposals for NSD's priors.

Static calibrated cameras and median backgrounds give, without any label, a
coarse *visual hull* of the individuals: a voxel of the working volume is
occupied when its projection shows foreground evidence (see
:func:`nsd.cues.evidence.foreground_evidence`, > 0.5) in every view that sees it, and
at least ``min_views`` views see it (by default a majority of the cameras,
:func:`hull_min_views`). The occupied voxels are counted per
column on the horizontal plane; the heaviest connected components of that map
(first one per group of nearby components) seed a k-means of the columns into
``k`` individuals (visual-hull *ghosts*,
the regions every camera sees as foreground without anything being there, are
lighter and dropped; pieces of one individual join it; a component holding
several touching individuals is cut; where bodies of unequal size touch, a Gaussian
mixture of the voxels in 3D replaces the k-means: :mod:`nsd.cues.clustering`). This
separates individuals that overlap in one view but not in another. Each
cluster, projected into each view, gives

* a proposal window: the extent of the foreground pixels the individual owns
  in that view (each foreground pixel goes to the nearest-in-depth individual
  whose voxels project close to it, see :func:`owned_pixels`; with few cameras the
  voxels of the individuals' cores first, :func:`outer_voxels`), divided by
  ``fill`` as in :mod:`nsd.cues.proposals`,
* its camera-space depth (mean over its voxels),
* an identity that is the same in every view of the frame (the cluster index), and
* the pixels the hull cannot settle: foreground pixels near the projections of two or
  more individuals (:func:`contested_pixels`), where touching or overlapping bodies meet.

These feed the proposal, depth and association priors of ``nsd-train``. The
working volume is, by default, a cube around the point closest to all optical
axes with half-size half the median camera distance to it; "up" is the mean of
the cameras' up directions (``-y`` of each camera). Ghost volumes of the
visual hull (regions seen as foreground by every camera without being
occupied) are possible with few cameras; they are low, and far ones are dropped.

Cost: the voxel projections are precomputed once (static cameras); per frame
the carving is one gather per view over the grid.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from nsd.cameras.calibration import CameraRig
from nsd.cameras.projection import project_points
from nsd.core.errors import ConfigError
from nsd.cues.clustering import (
    ClusterTrack,
    MixtureRules,
    cluster_individuals,
    scene_wants_mixture,
)

__all__ = [
    "CONTEST_BAND",
    "MultiviewProposals",
    "VoxelGrid",
    "candidate_individuals",
    "contested_pixels",
    "hull_individuals",
    "hull_min_views",
    "multiview_proposals",
    "occupied_voxels",
    "outer_voxels",
    "owned_pixels",
    "scene_gains",
    "scene_track",
    "voxel_grid",
    "working_volume",
]


class MultiviewProposals(NamedTuple):
    """Visual-hull proposals of one frame.

    Attributes:
        boxes: windows (V, k, 4) = (sx, sy, tx, ty), normalised.
        depths: camera-space depth of each individual in each view (V, k).
        valid: (V, k) bool.
        owners: the individual owning each foreground pixel (V, H, W), -1 elsewhere.
        candidates: (V, k, H, W) bool, the individuals near each foreground pixel
            (:func:`candidate_individuals`); a pixel with two or more is contested.
    """

    boxes: Tensor
    depths: Tensor
    valid: Tensor
    owners: Tensor
    candidates: Tensor

    @property
    def contested(self) -> Tensor:
        """(V, H, W) bool: foreground pixels near two or more individuals."""
        return self.candidates.sum(1) >= 2


@dataclass
class VoxelGrid:
    """A voxel grid over the working volume and its projections into every view.

    Attributes:
        centres: voxel centres (M, 3), world.
        size: voxel side (scene units).
        pixel: flat pixel index of each voxel in each view (V, M), int64.
        inside: the voxel projects inside view v (and in front of it), (V, M) bool.
        uv: projected pixel coordinates (V, M, 2).
        depth: camera-space depth (V, M).
        up: world up direction (3,).
        focal: mean focal length of each view in pixels (V,).
        image_size: (H, W).
        min_views: views that must see a voxel for it to be carved (:func:`hull_min_views`).
    """

    centres: Tensor
    size: float
    pixel: Tensor
    inside: Tensor
    uv: Tensor
    depth: Tensor
    up: Tensor
    focal: Tensor
    image_size: tuple[int, int]
    min_views: int


def working_volume(rig: CameraRig) -> tuple[np.ndarray, float, np.ndarray]:
    """Default working volume: (centre (3,), half-size, up (3,)) from the cameras' poses."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in rig:
        P = np.eye(3) - np.outer(c.viewing_direction, c.viewing_direction)
        A += P
        b += P @ c.center
    focus = np.linalg.lstsq(A, b, rcond=None)[0]
    half = 0.5 * float(np.median([np.linalg.norm(c.center - focus) for c in rig]))
    up = -np.mean([c.R[1] for c in rig], axis=0)
    return focus, half, up / np.linalg.norm(up)


def hull_min_views(num_views: int, setting: int | str = "auto", key: str = "min_views") -> int:
    """Views that must see a voxel (and all of them show foreground there) for the hull to
    hold it: ``auto`` is a majority of the cameras (2 of 2 or 3, 3 of 4, 4 of 6, 5 of 8).

    A voxel seen by two cameras only is carved by two silhouettes: near the edges of the
    cameras' fields, where few see, such voxels form ghost bodies between and beside the
    individuals that join them in one component or take their slots
    (docs/benchmarks/hull.md: hull-only detection with 2 of 6 cameras 0.55, with 4 of 6 1.00).
    A number is used as given (at least 2, at most ``num_views``); ``key`` names the setting
    in the error.
    """
    if setting == "auto":
        return max(2, num_views // 2 + 1) if num_views >= 2 else num_views
    n = int(setting)
    if not 2 <= n <= max(2, num_views):
        raise ConfigError(f"{key} must be auto or between 2 and the {num_views} cameras, "
                          f"got {setting!r}")
    return n


def voxel_grid(
    rig: CameraRig,
    image_size: tuple[int, int],
    resolution: int = 48,
    centre: np.ndarray | None = None,
    half_size: float | None = None,
    min_views: int | str = "auto",
    key: str = "min_views",
) -> VoxelGrid:
    """Precompute a ``resolution``^3 grid over the working volume and its projections.

    Args:
        rig: cameras scaled to the frames' size.
        image_size: (H, W) of the frames.
        resolution: voxels per side.
        centre, half_size: working volume (default: :func:`working_volume`).
        min_views: :func:`hull_min_views`' setting; ``key`` its name in an error.
    """
    focus, half, up = working_volume(rig)
    centre = focus if centre is None else np.asarray(centre, float)
    half = half if half_size is None else float(half_size)
    size = 2 * half / resolution
    ax = (np.arange(resolution) + 0.5) * size - half
    g = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) + centre
    centres = torch.as_tensor(g, dtype=torch.float32)
    cams = rig.stacked(torch.float32)
    uv, z = project_points(
        centres.expand(len(rig), -1, -1), cams.K, cams.R, cams.t, cams.dist
    )
    H, W = image_size
    u, v = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    pixel = (v.clamp(0, H - 1) * W + u.clamp(0, W - 1)).long()
    focal = (cams.K[:, 0, 0] + cams.K[:, 1, 1]) / 2
    return VoxelGrid(
        centres, size, pixel, inside, uv, z, torch.as_tensor(up, dtype=torch.float32), focal,
        (H, W), hull_min_views(len(rig), min_views, key),
    )


def occupied_voxels(
    evidence: Tensor, grid: VoxelGrid, min_views: int | None = None, threshold: float = 0.5
) -> Tensor:
    """Visual-hull occupancy of one frame.

    Args:
        evidence: foreground evidence of every view (V, H, W).
        grid: the precomputed grid.
        min_views: a voxel must be seen by at least this many views (None: the grid's).
        threshold: evidence above which a pixel is foreground.

    Returns:
        (M,) bool.
    """
    min_views = grid.min_views if min_views is None else min_views
    fg = evidence.flatten(1) > threshold  # (V, P)
    hit = torch.gather(fg, 1, grid.pixel)  # (V, M)
    seen = grid.inside.sum(0)
    return ((hit | ~grid.inside).all(0)) & (seen >= min_views) & (hit & grid.inside).any(0)


# owned_pixels' radius and reach in voxel sides (a voxel's side in pixels at the median depth
# of the view's voxels). A radius of 1.5 gave every pixel within a voxel and a half of an
# individual's hull to the front-most one, so the front individual's hull, fat along the rays
# of the views that do not carve it, took the rims of those behind it: 0.6 (about a voxel's
# footprint); put back to 1.5, hull-only detection of three huddling bipeds falls 0.98 -> 0.83
# and the merge rate rises 0.28 -> 0.84 (docs/benchmarks/hull.md).
OWNER_RADIUS = 0.6
OWNER_REACH = 4.5
# contested_pixels' band in voxel sides: on the held-out frames of three huddling bipeds,
# 54 % of the visible foreground lies within 1.5 voxel sides of two individuals; there the
# hull's owner is right for 71 % of the pixels and the trained auto-encoder's ownership for
# 81 %, elsewhere for 96 % and 93 % (docs/nsd.md, "Where the hull cannot settle").
CONTEST_BAND = 1.5
# With few cameras the hull holds *excess*: voxels that every camera sees as foreground
# because other bodies lie behind or in front of them along each ray (ghosts between
# touching bodies, and each body's hull fat along the rays no camera carves). A ghost
# labelled with the body beside it took, as the front-most voxel of a pixel, the pixels
# of the body behind it. On 4 cameras a pixel now goes to the front-most voxel of the
# individuals' *cores* near it, where there is one: the voxels within CORE_SPREAD squared
# Mahalanobis distances of the Gaussian (mean, covariance) of their individual's voxels in
# that frame (4: about three in four voxels of a Gaussian are core); else to the front-most
# voxel as before. Hull-only mask mIoU on all ten scenes of 4 cameras +0.012 to +0.035;
# on the 20 of 6 and 8 cameras, where the hull is carved closer, -0.013 to -0.002: the
# cores own first up to CORE_MAX_VIEWS cameras (docs/nsd.md, "The hull's excess";
# docs/benchmarks/hull_cores.md). On five rings of 5 cameras the cores first moved mask mIoU
# -0.003 to +0.002, on two rings of 4 +0.025 and +0.019 (docs/benchmarks/hull_cores_rings.md).
CORE_SPREAD = 4.0
CORE_MAX_VIEWS = 4
# The excess inflates the Gaussian of all an individual's voxels; estimated again once from
# the voxels it left inside (the core) before the final cut, hull-only mask mIoU on 11 of
# 12 scenes of 4 cameras +0.0003 to +0.007, on one -0.004; twice, no better
# (docs/nsd.md, "The cores from their own Gaussian"; docs/benchmarks/hull_core_refits.md).
CORE_REFITS = 1


class _PixelVoxels(NamedTuple):
    """Which voxel projections lie near which foreground pixels of one view
    (:func:`_pixel_voxels`): the pixels' rows and columns ``ys``, ``xs`` (F,), each pixel's
    nearest voxel ``nearest`` (F,) and its distance ``nearest_distance`` (F,) (inf beyond
    the reach asked), and every pixel-voxel pair within the band asked: pixel
    ``pair_pixel`` (E,), voxel ``pair_voxel`` (E,), distance ``pair_distance`` (E,)."""

    ys: Tensor
    xs: Tensor
    nearest: np.ndarray
    nearest_distance: np.ndarray
    pair_pixel: np.ndarray
    pair_voxel: np.ndarray
    pair_distance: np.ndarray


def _pixel_voxels(fg: Tensor, uv: Tensor, band: float, reach: float) -> _PixelVoxels:
    """The foreground pixels of ``fg`` (H, W) bool against the voxels' projections ``uv``
    (P, 2) (x, y): pairs within ``band`` pixels and each pixel's nearest voxel within
    ``reach`` (both inclusive, distances in float64). A k-d tree of each
    (``scipy.spatial.cKDTree``) instead of the (F, P) matrix of all distances: an 8-camera
    group's hull has ~2,000 foreground pixels and ~2,000 voxels per view, and the dense
    matrix, its masks and arg-minima were half of the training's hull proposals."""
    ys, xs = torch.nonzero(fg, as_tuple=True)
    pix = np.stack([xs.numpy(), ys.numpy()], -1).astype(np.float64)
    pts = uv.detach().double().numpy()
    empty = np.zeros(0, np.int64)
    if len(pix) == 0 or len(pts) == 0:
        none = np.full(len(pix), np.inf)
        return _PixelVoxels(ys, xs, np.zeros(len(pix), np.int64), none, empty, empty,
                           np.zeros(0))
    voxels = cKDTree(pts)
    dist, nearest = voxels.query(pix, k=1, distance_upper_bound=np.nextafter(reach, np.inf))
    # every pair at most band apart (sparse_distance_matrix keeps distances <= its bound)
    pairs = cKDTree(pix).sparse_distance_matrix(voxels, band, output_type="ndarray")
    nearest = np.where(np.isfinite(dist), nearest, 0).astype(np.int64)
    return _PixelVoxels(ys, xs, nearest, dist, pairs["i"].astype(np.int64),
                        pairs["j"].astype(np.int64), pairs["v"])


def outer_voxels(x: Tensor, labels: Tensor, k: int, spread: float = CORE_SPREAD,
                 refits: int | None = None) -> Tensor:
    """The voxels outside their individual's core: (P,) bool, True where the squared
    Mahalanobis distance of voxel centre ``x`` (P, 3) to the Gaussian (mean, covariance) of
    the voxels of its label (``labels`` (P,) in [0, ``k``), -1 none) exceeds ``spread``.
    Labels of fewer than 8 voxels (too few for a covariance) and voxels without a label
    are never outer. With ``refits`` (None: ``CORE_REFITS``) the Gaussian is estimated
    again that many times from the voxels it left inside (its core) and the cut made again
    (while at least 8 remain).

    Example:
        >>> cube = torch.tensor([-1.0, 0.0, 1.0])
        >>> x = torch.stack(torch.meshgrid(cube, cube, cube, indexing="ij"), -1).reshape(-1, 3)
        >>> x = torch.cat([x, torch.tensor([[8.0, 0.0, 0.0]])])  # 27 voxels and a far one
        >>> one = torch.zeros(28, dtype=torch.long)
        >>> outer_voxels(x, one, 1, refits=0).nonzero().flatten().tolist()
        [27]
        >>> len(outer_voxels(x, one, 1).nonzero())  # refitted: the cube's 8 corners too (4.5)
        9
    """
    refits = CORE_REFITS if refits is None else refits
    out = torch.zeros(len(labels), dtype=torch.bool)
    xs, lab = x.double().numpy(), labels.numpy()
    for j in range(k):
        own = np.flatnonzero(lab == j)
        if len(own) < 8:
            continue
        core = np.ones(len(own), bool)
        for _ in range(refits + 1):
            if core.sum() < 8:  # too few for a covariance: the last cut stands
                break
            inside = xs[own[core]]
            mean = inside.mean(0)
            d = inside - mean
            cov = d.T @ d / len(d) + 1e-9 * np.eye(3)
            e = xs[own] - mean
            core = np.einsum("ni,ij,nj->n", e, np.linalg.inv(cov), e) <= spread
        out[torch.from_numpy(own[~core])] = True
    return out


def _owners(shape: tuple[int, int], near: _PixelVoxels, depth: Tensor, labels: Tensor,
            radius: float, reach: float, outer: Tensor | None = None) -> Tensor:
    """:func:`owned_pixels` from :func:`_pixel_voxels` (its band >= ``radius``, its reach
    >= ``reach``); ``outer`` (P,) bool: voxels that own a pixel only where no core voxel
    (not outer) lies within the radius (None: every voxel is core)."""
    owner = torch.full(shape, -1, dtype=torch.long)
    if len(near.ys) == 0 or len(labels) == 0:
        return owner
    close = near.pair_distance <= radius
    pi, pj = near.pair_pixel[close], near.pair_voxel[close]
    # each pixel's front-most voxel within the radius (the lowest index of equal depths),
    # of the cores first
    rank = np.zeros(len(labels)) if outer is None else outer.numpy().astype(np.float64)
    order = np.lexsort((pj, depth.numpy().astype(np.float64)[pj], rank[pj], pi))
    pi, pj = pi[order], pj[order]
    first = np.ones(len(pi), bool)
    first[1:] = pi[1:] != pi[:-1]
    front = np.full(len(near.ys), -1, np.int64)
    front[pi[first]] = pj[first]
    has_near = front >= 0
    pick = np.where(has_near, front, near.nearest)
    ok = torch.from_numpy(has_near | (near.nearest_distance <= reach))
    owner[near.ys[ok], near.xs[ok]] = labels[torch.from_numpy(pick)[ok]]
    return owner


def _candidates(shape: tuple[int, int], near: _PixelVoxels, labels: Tensor, k: int,
                band: float) -> Tensor:
    """:func:`candidate_individuals` from :func:`_pixel_voxels` (its band >= ``band``)."""
    out = torch.zeros(k, *shape, dtype=torch.bool)
    close = near.pair_distance <= band
    pi = torch.from_numpy(near.pair_pixel[close])
    pj = torch.from_numpy(near.pair_voxel[close])
    out[labels[pj], near.ys[pi], near.xs[pi]] = True
    return out


def owned_pixels(
    fg: Tensor,
    uv: Tensor,
    depth: Tensor,
    labels: Tensor,
    k: int,
    radius: float,
    reach: float,
    outer: Tensor | None = None,
) -> Tensor:
    """Give each foreground pixel of one view to an individual.

    A pixel goes to the nearest-in-depth individual among the voxels projecting
    within ``radius`` pixels of it (among those not ``outer``, where there is one),
    else to the individual of the nearest voxel within ``reach`` pixels (limbs the
    coarse hull lost), else to nobody.

    Args:
        fg: foreground (H, W) bool.
        uv: projections of the individuals' voxels (P, 2); depth (P,); labels (P,).
        k: number of individuals.
        radius, reach: pixels.
        outer: (P,) bool, voxels outside their individual's core (:func:`outer_voxels`);
            None: none.

    Returns:
        owner map (H, W) int64 in [-1, k).
    """
    return _owners(fg.shape, _pixel_voxels(fg, uv, radius, reach), depth, labels, radius,
                   reach, outer)


def candidate_individuals(fg: Tensor, uv: Tensor, labels: Tensor, k: int,
                          band: float) -> Tensor:
    """The individuals whose voxels project near each foreground pixel of one view.

    Args:
        fg: foreground (H, W) bool.
        uv: projections of the individuals' voxels (P, 2); labels (P,) in [0, k).
        k: number of individuals.
        band: pixels.

    Returns:
        (k, H, W) bool: individual ``j`` has a voxel projecting within ``band`` pixels of
        the foreground pixel.
    """
    return _candidates(fg.shape, _pixel_voxels(fg, uv, band, 0.0), labels, k, band)


def contested_pixels(fg: Tensor, uv: Tensor, labels: Tensor, k: int, band: float) -> Tensor:
    """The foreground pixels of one view near two or more individuals' voxels: (H, W) bool
    (arguments as :func:`candidate_individuals`)."""
    return candidate_individuals(fg, uv, labels, k, band).sum(0) >= 2


def hull_individuals(
    evidence: Tensor,
    grid: VoxelGrid,
    k: int,
    min_voxels: int = 4,
    min_views: int | None = None,
    split: bool = True,
    track: ClusterTrack | None = None,
) -> tuple[Tensor, Tensor]:
    """The occupied voxels of one frame (evidence (V, H, W)) and their individuals: flat
    grid indices (P,) and labels (P,) in [0, k) or -1 (:func:`cluster_individuals`, which
    moves ``track`` on by this frame); every label -1 (``track`` untouched) with fewer than
    ``min_voxels``. What :func:`multiview_proposals` clusters, alone: one process can carry
    the track through the frames and hand the labels to those that compute the proposals."""
    idx = torch.nonzero(occupied_voxels(evidence, grid, min_views)).flatten()
    if len(idx) < min_voxels:
        return idx, torch.full((len(idx),), -1, dtype=torch.long)
    return idx, cluster_individuals(grid.centres[idx], grid.up, grid.size, k, split=split,
                                    track=track)


def scene_track(
    evidence: Callable[[int], Tensor],
    instants: Sequence[int],
    grid: VoxelGrid,
    k: int,
    split: bool = True,
    min_views: int | None = None,
    rules: MixtureRules | None = None,
) -> ClusterTrack:
    """A :class:`ClusterTrack` to carry through a scene's ``instants``, with its ``mixture``
    decided ahead (:func:`nsd.cues.clustering.scene_wants_mixture`) from the hulls of
    ``rules.mixture_scene_sample`` of them spread evenly (``rules``: None, the shipped
    defaults; the returned track carries them), ``evidence(t)`` (V, H, W) each: one decision
    for the scene, taken before its first instant (a running one lags where the first
    instants gain little). Without ``split`` (``k`` an upper bound) no mixture is fitted
    and nothing is read."""
    track = ClusterTrack(rules=rules)
    if split and len(instants):
        gains = scene_gains(evidence, instants, grid, k, min_views, track.rules)
        track.mixture = scene_wants_mixture(gains, track.rules.mixture_scene_gain)
    return track


def scene_gains(
    evidence: Callable[[int], Tensor],
    instants: Sequence[int],
    grid: VoxelGrid,
    k: int,
    min_views: int | None = None,
    rules: MixtureRules | None = None,
) -> list[float]:
    """The 3D mixture's gains over the k-means (nats per voxel) that :func:`scene_track`
    decides from: the hulls of ``rules.mixture_scene_sample`` of ``instants`` spread
    evenly, clustered in turn with one track carried through them (``rules``: None, the
    shipped defaults); instants whose bodies stand apart give none."""
    track = ClusterTrack(rules=rules)
    spread = np.linspace(0, len(instants) - 1, track.rules.mixture_scene_sample)
    for i in np.unique(spread.round().astype(int)):
        hull_individuals(evidence(int(instants[i])), grid, k, min_views=min_views,
                         track=track)
    return list(track.gains)


def multiview_proposals(
    evidence: Tensor,
    grid: VoxelGrid,
    k: int,
    fill: float = 0.75,
    min_voxels: int = 4,
    min_scale: float = 0.2,
    max_scale: float = 1.0,
    min_views: int | None = None,
    split: bool = True,
    contest: float = 0.0,
    track: ClusterTrack | None = None,
    clustered: tuple[Tensor, Tensor] | None = None,
) -> MultiviewProposals:
    """Proposals for all views of one frame from its occupancy.

    Args:
        evidence: (V, H, W) foreground evidence.
        grid: precomputed voxel grid.
        k: number of clusters (windows).
        fill: fraction of the window half-size the subject fills (as nsd.cues.proposals).
        min_voxels: smaller clusters are invalid.
        min_scale, max_scale: bounds of proposal scales.
        min_views: as in :func:`occupied_voxels`.
        split: :func:`cluster_individuals`' ``split`` (False: ``k`` is an upper bound
            and slots without an individual are invalid).
        contest: :func:`contested_pixels`' band in voxel sides (e.g. ``CONTEST_BAND``;
            0: not computed, ``contested`` is all False).
        track: carried from the previous frame of a sequence (:func:`cluster_individuals`).
        clustered: this frame's :func:`hull_individuals`, computed elsewhere (None: here).

    Returns:
        :class:`MultiviewProposals`. Slot ``j`` is the same cluster (individual) in
        every view. A window covers the foreground pixels its individual owns
        (:func:`owned_pixels`).
    """
    V = evidence.shape[0]
    H, W = grid.image_size
    boxes = torch.zeros(V, k, 4)
    boxes[..., :2] = min_scale
    depths = torch.zeros(V, k)
    valid = torch.zeros(V, k, dtype=torch.bool)
    owners = torch.full((V, H, W), -1, dtype=torch.long)
    candidates = torch.zeros(V, k, H, W, dtype=torch.bool)
    if clustered is None:
        clustered = hull_individuals(evidence, grid, k, min_voxels, min_views, split, track)
    idx, labels = clustered
    keep = labels >= 0
    if not keep.any():
        return MultiviewProposals(boxes, depths, valid, owners, candidates)
    idx, labels = idx[keep], labels[keep]
    # few cameras: the cores own first (CORE_SPREAD)
    outer = outer_voxels(grid.centres[idx], labels, k) if V <= CORE_MAX_VIEWS else None
    f = grid.uv.new_tensor([W, H]) / 2  # pixels per normalised unit
    for v in range(V):
        vis = grid.inside[v, idx]
        z = grid.depth[v, idx[vis]]
        voxel_px = float(grid.size * grid.focal[v] / z.median()) if len(z) else 1.0
        radius, reach, band = (OWNER_RADIUS * voxel_px, OWNER_REACH * voxel_px,
                               contest * voxel_px)
        near = _pixel_voxels(evidence[v] > 0.5, grid.uv[v, idx[vis]], max(radius, band),
                             reach)  # once for both
        owners[v] = _owners((H, W), near, z, labels[vis], radius, reach,
                            None if outer is None else outer[vis])
        if contest > 0:
            candidates[v] = _candidates((H, W), near, labels[vis], k, band)
        for j in range(k):
            sel = labels[vis] == j
            ys, xs = torch.nonzero(owners[v] == j, as_tuple=True)
            if sel.sum() < min_voxels or len(xs) < min_voxels:
                continue
            pts = torch.stack([xs, ys], -1).to(f.dtype)
            lo = torch.quantile(pts, 0.01, dim=0) - 0.5
            hi = torch.quantile(pts, 0.99, dim=0) + 0.5
            centre = (lo + hi) / 2 / f - 1
            half = (hi - lo) / 2 / f / fill
            boxes[v, j] = torch.cat([half.clamp(min_scale, max_scale), centre])
            depths[v, j] = z[sel].mean()
            valid[v, j] = True
    return MultiviewProposals(boxes, depths, valid, owners, candidates)
