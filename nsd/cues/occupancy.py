r"""Multi-view occupancy from background residuals: label-free 3D proposals for NSD's priors.

Static calibrated cameras and median backgrounds give, without any label, a
coarse *visual hull* of the individuals: a voxel of the working volume is
occupied when its projection shows foreground evidence (see
:func:`nsd.cues.evidence.foreground_evidence`, > 0.5) in every view that sees it, and
at least ``min_views`` views see it (by default a majority of the cameras,
:func:`hull_min_views`). The occupied voxels are counted per
column on the horizontal plane; the ``k`` heaviest connected components of that
map seed a k-means of the columns into ``k`` individuals (visual-hull *ghosts*,
the regions every camera sees as foreground without anything being there, are
lighter and dropped; pieces of one individual join it; a component holding
several touching individuals is cut; where bodies of unequal size touch, a Gaussian
mixture of the voxels in 3D replaces the k-means, :func:`cluster_individuals`). This
separates individuals that overlap in one view but not in another. Each
cluster, projected into each view, gives

* a proposal window: the extent of the foreground pixels the individual owns
  in that view (each foreground pixel goes to the nearest-in-depth individual
  whose voxels project close to it, see :func:`owned_pixels`), divided by
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

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage
from scipy.stats import multivariate_normal
from threadpoolctl import threadpool_limits
from torch import Tensor

from nsd.cameras.calibration import CameraRig
from nsd.cameras.projection import project_points
from nsd.core.errors import ConfigError
from nsd.ops.vectors import up_frame

__all__ = [
    "CONTEST_BAND",
    "MultiviewProposals",
    "VoxelGrid",
    "candidate_individuals",
    "cluster_individuals",
    "contested_pixels",
    "hull_min_views",
    "multiview_proposals",
    "occupied_voxels",
    "owned_pixels",
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
# cluster_individuals with the count known: seeds of the k-means at least SEED_SPREAD typical
# radii apart; columns beyond GHOST_SPREAD radii of their cluster dropped. With 1.5 radii,
# hull-only detection of six huddling bipeds 0.95 -> 0.93, of the mixed group 0.62 -> 0.59
# (docs/benchmarks/hull.md); 4 was chosen on the scenes of that table.
SEED_SPREAD = 4.0
GHOST_SPREAD = 3.0
KMEANS_ITERATIONS = 10
# then a Gaussian mixture of the voxels in 3D (full covariances: a long, low quadruped beside
# upright bipeds), the best of fits from the k-means partition and from MIXTURE_RESTARTS
# k-means++ starts, replaces the k-means where it explains the voxels better than Gaussians
# fitted to the k-means partition by at least MIXTURE_GAIN nats per voxel. The k-means cuts
# bodies of unequal size at the midpoint between centres: on the mixed group (2 bipeds, 2
# quadrupeds) hull-only detection 0.58 -> 0.80 and mask mIoU 0.47 -> 0.67. Always taking the
# mixture costs equal bipeds that touch (3 bipeds: detection 0.98 -> 0.94); at 0.02, over ten
# scenes, voxel labels are never more than 0.005 below the k-means' and 0.13-0.27 above them
# with quadrupeds; 0.05 lost half the gain on scenes the rule was not chosen on (docs/nsd.md,
# "Bodies of unequal size"; docs/benchmarks/hull_mixture.md).
MIXTURE_RESTARTS = 10
MIXTURE_GAIN = 0.02
MIXTURE_ITERATIONS = 100


def _weighted_rms(x: np.ndarray, centre: np.ndarray, w: np.ndarray, floor: float) -> float:
    """Weighted RMS distance of points ``x`` (C, 2) to ``centre``, at least ``floor``."""
    return max(floor, float(np.sqrt(np.average(((x - centre) ** 2).sum(1), weights=w))))


def _split_heaviest(xy: np.ndarray, w: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """One more centre (C + 1, 2): the heaviest cluster's centre moved half a standard
    deviation each way along its principal axis."""
    lab = np.linalg.norm(xy[:, None] - centres[None], axis=2).argmin(1)
    j = int(np.bincount(lab, weights=w, minlength=len(centres)).argmax())
    x, wj = xy[lab == j], w[lab == j]
    mu = np.average(x, axis=0, weights=wj)
    cov = np.cov((x - mu).T, aweights=wj) if len(x) > 1 else np.zeros((2, 2))
    values, vectors = np.linalg.eigh(np.atleast_2d(cov))
    step = 0.5 * np.sqrt(max(float(values[-1]), 1e-12)) * vectors[:, -1]
    centres = centres.copy()
    centres[j] = mu - step
    return np.vstack([centres, mu + step])


def _seeded_columns(cxy: np.ndarray, w: np.ndarray, comp: np.ndarray, n: int, k: int,
                    cell: float) -> np.ndarray:
    """Labels (C,) in [0, k) or -1 of the plane's columns (centres ``cxy`` (C, 2), weights
    ``w`` (C,), components ``comp`` (C,) in [0, n)) for ``k`` individuals (see
    :func:`cluster_individuals`)."""
    score = np.bincount(comp, weights=w, minlength=n)
    centre = np.stack([np.average(cxy[comp == c], axis=0, weights=w[comp == c])
                       for c in range(n)])
    rms = np.array([_weighted_rms(cxy[comp == c], centre[c], w[comp == c], cell)
                    for c in range(n)])
    order = np.argsort(-score)
    apart = SEED_SPREAD * float(np.median(rms[order[:k]]))
    seeds: list[int] = []
    for c in order:
        if len(seeds) == k:
            break
        if all(np.linalg.norm(centre[c] - centre[s]) >= apart for s in seeds):
            seeds.append(int(c))
    centres = centre[seeds]
    while len(centres) < k:
        centres = _split_heaviest(cxy, w, centres)
    for _ in range(KMEANS_ITERATIONS):
        lab = np.linalg.norm(cxy[:, None] - centres[None], axis=2).argmin(1)
        for j in range(k):
            if (lab == j).any():
                centres[j] = np.average(cxy[lab == j], axis=0, weights=w[lab == j])
    d = np.linalg.norm(cxy[:, None] - centres[None], axis=2)
    lab = d.argmin(1)
    spread = np.array([_weighted_rms(cxy[lab == j], centres[j], w[lab == j], cell)
                       if (lab == j).any() else cell for j in range(k)])
    lab[d[np.arange(len(lab)), lab] > GHOST_SPREAD * spread[lab]] = -1
    rank = np.empty(k, np.int64)
    rank[np.argsort(centres[:, 0], kind="stable")] = np.arange(k)  # a stable order
    return np.where(lab >= 0, rank[lab], -1)


def _partition_loglik(x: np.ndarray, labels: np.ndarray, k: int, reg: float) -> float:
    """Mean log-likelihood (nats per point) of ``x`` (P, D) under the Gaussian mixture
    fitted to the hard partition ``labels`` (P,) in [0, k): each part's mean and covariance
    (plus ``reg`` on the diagonal), weights by size."""
    logp = [np.log((labels == j).mean())
            + multivariate_normal(x[labels == j].mean(0),
                                  np.cov(x[labels == j].T) + reg * np.eye(x.shape[1])).logpdf(x)
            for j in range(k) if (labels == j).sum() > x.shape[1]]
    return float(np.logaddexp.reduce(np.stack(logp), axis=0).mean()) if logp else -np.inf


def _mixture_labels(x: np.ndarray, labels: np.ndarray, k: int, reg: float,
                    gain: float) -> np.ndarray | None:
    """Labels (P,) in [0, k) of ``x`` (P, D) by a Gaussian mixture (full covariances,
    ``reg`` added to them), or None where it does not explain ``x`` better than the
    partition ``labels`` (P,) in [0, k) does (:func:`_partition_loglik`).

    The best of the mixtures started from the partition and from ``MIXTURE_RESTARTS``
    k-means++ seeds must gain ``gain`` nats per point.
    """
    # lazy: scikit-learn (1.9 s to import) only where the hull's k-means may have cut a body
    from sklearn.mixture import GaussianMixture

    def fit(**start) -> GaussianMixture:
        return GaussianMixture(k, covariance_type="full", reg_covar=reg,
                               max_iter=MIXTURE_ITERATIONS, **start).fit(x)

    # one BLAS thread: on these small matrices, threads contending with torch's idle ones
    # made a held-out frame of the default scene's hull 0.10 s instead of 0.04
    with threadpool_limits(1):
        base = _partition_loglik(x, labels, k, reg)
        means = np.stack([x[labels == j].mean(0) if (labels == j).any() else x.mean(0)
                          for j in range(k)])
        fits = [fit(means_init=means, random_state=0)]
        fits += [fit(init_params="k-means++", random_state=s) for s in range(MIXTURE_RESTARTS)]
        scores = [g.score(x) for g in fits]
        if max(scores) - base < gain:
            return None
        return fits[int(np.argmax(scores))].predict(x)


def _mixture_relabelled(x: np.ndarray, plane: np.ndarray, labels: np.ndarray, k: int,
                        reg: float, gain: float) -> np.ndarray:
    """``labels`` (P,) in [0, k) or -1 of the points ``x`` (P, 3) (``plane`` (P, 2): their
    ground-plane coordinates) with the kept ones (>= 0) replaced by the mixture's
    (:func:`_mixture_labels`), ranked along the first plane axis; unchanged where the
    mixture does not gain ``gain`` or the partition has fewer than ``k`` parts."""
    keep = labels >= 0
    if len(np.unique(labels[keep])) < k or keep.sum() <= 4 * k:
        return labels
    mixed = _mixture_labels(x[keep], labels[keep], k, reg, gain)
    if mixed is None:
        return labels
    centres = np.stack([plane[keep][mixed == j].mean(0) if (mixed == j).any()
                        else np.full(2, np.inf) for j in range(k)])
    rank = np.empty(k, np.int64)
    rank[np.argsort(centres[:, 0], kind="stable")] = np.arange(k)  # a stable order
    out = labels.copy()
    out[keep] = rank[mixed]
    return out


def cluster_individuals(
    points: Tensor,
    up: Tensor,
    cell: float,
    k: int,
    min_column: int = 2,
    split: bool = True,
    ghost_ratio: float = 0.2,
    mixture_gain: float | None = None,
) -> Tensor:
    """Individual labels (P,) in [0, k) or -1 (dropped) for occupied voxel centres (P, 3).

    Columns of the horizontal plane (side ``cell``) holding at least ``min_column``
    voxels are grouped into 4-connected components, weighted by their squared column
    heights (tall bodies over low ghosts).

    With ``split`` (``k`` is the number of individuals), the components seed a weighted
    k-means of the columns: the heaviest components whose centres lie at least
    ``SEED_SPREAD`` typical radii apart (the median weighted RMS radius of the ``k``
    heaviest components: the scale of an individual in this scene, whatever its units or
    species) are seeds; while there are fewer than ``k``, the heaviest cluster is cut in
    two along its principal axis; k-means then moves the ``k`` centres and every column
    goes to the nearest. The pieces an individual's hull falls into (legs apart, a thin
    waist) join their body instead of taking the slot of an individual merged with
    another, and a huddle is cut where the columns' mass says. Columns farther than
    ``GHOST_SPREAD`` times their cluster's RMS radius from its centre are dropped (ghosts).
    The k-means assumes bodies of one size. Unless each cluster is one whole component
    (individuals apart), where a Gaussian mixture of the kept voxels in 3D explains them
    better by ``mixture_gain`` nats per voxel (None: ``MIXTURE_GAIN``; ``inf``: never;
    ``-inf``: always), its labels replace the k-means': a long quadruped is not cut at
    the midpoint to an upright neighbour.

    Without (``k`` is only an upper bound), the ``k`` heaviest components are the
    individuals, nothing is split and components scoring below ``ghost_ratio`` times the
    heaviest are dropped as ghosts: the labels then say how many individuals the hull
    holds, instead of cutting one individual into ``k`` parts.
    """

    xy = points @ up_frame(up)[:, :2]  # (P, 2): coordinates in the plane orthogonal to up
    ij = torch.floor((xy - xy.min(0).values) / cell).long()
    shape = (int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1)
    counts = np.zeros(shape)
    np.add.at(counts, (ij[:, 0].numpy(), ij[:, 1].numpy()), 1)
    # thin columns (one voxel) are hull noise and bridge neighbours: drop them
    kept = counts >= min_column
    comp, n = ndimage.label(kept)
    labels = torch.full((len(points),), -1, dtype=torch.long)
    if n == 0:
        return labels
    if split:
        column = np.full(shape, -1, np.int64)
        column[kept] = _seeded_columns((np.argwhere(kept) + 0.5) * cell, counts[kept] ** 2,
                                       comp[kept] - 1, n, k, cell)
        labels = column[ij[:, 0].numpy(), ij[:, 1].numpy()]
        gain = MIXTURE_GAIN if mixture_gain is None else mixture_gain
        pairs = np.unique(np.stack([comp[kept], column[kept]], 1)[column[kept] >= 0], axis=0)
        # each individual one whole component (apart): nothing for the mixture to mend
        whole = len(pairs) == k and len(np.unique(pairs[:, 0])) == k
        if gain < np.inf and (not whole or gain == -np.inf):
            labels = _mixture_relabelled(points.double().numpy(), xy.double().numpy(), labels,
                                         k, cell**2, gain)
        return torch.as_tensor(labels)
    point_comp = torch.as_tensor(comp[ij[:, 0].numpy(), ij[:, 1].numpy()]) - 1  # (P,)
    groups = [torch.nonzero(point_comp == c).flatten() for c in range(n)]
    # rank by sum of squared column heights: people are tall, ghosts are low and flat
    score = [float((counts[comp == c + 1] ** 2).sum()) for c in range(n)]
    ranked = sorted(zip(score, groups, strict=True), key=lambda p: -p[0])[:k]
    ranked = [(sc, g) for sc, g in ranked if sc >= ghost_ratio * ranked[0][0]]
    groups = [g for _, g in ranked]
    # a stable order: by position along the first plane axis
    groups.sort(key=lambda g: float(xy[g, 0].mean()) if len(g) else 0.0)
    for j, g in enumerate(groups):
        labels[g] = j
    return labels


def _pixel_distances(fg: Tensor, uv: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The foreground pixels' rows and columns (F,) and their distances to the voxels'
    projections uv (P, 2): (F, P)."""
    ys, xs = torch.nonzero(fg, as_tuple=True)
    pix = torch.stack([xs, ys], -1).to(uv.dtype)
    return ys, xs, torch.cdist(pix, uv)


def _owners(shape: tuple[int, int], ys: Tensor, xs: Tensor, d: Tensor, depth: Tensor,
            labels: Tensor, radius: float, reach: float) -> Tensor:
    """:func:`owned_pixels` from :func:`_pixel_distances`."""
    owner = torch.full(shape, -1, dtype=torch.long)
    if d.numel() == 0:
        return owner
    near = d <= radius
    zbuf = torch.where(near, depth[None].expand_as(d), torch.full_like(d, float("inf")))
    front = zbuf.argmin(1)
    nearest = d.argmin(1)
    has_near = near.any(1)
    pick = torch.where(has_near, front, nearest)
    ok = has_near | (d.gather(1, nearest[:, None])[:, 0] <= reach)
    owner[ys[ok], xs[ok]] = labels[pick[ok]]
    return owner


def _candidates(shape: tuple[int, int], ys: Tensor, xs: Tensor, d: Tensor, labels: Tensor,
                k: int, band: float) -> Tensor:
    """:func:`candidate_individuals` from :func:`_pixel_distances`."""
    out = torch.zeros(k, *shape, dtype=torch.bool)
    if d.numel() == 0:
        return out
    nearest = d.new_full((len(ys), k), float("inf"))
    nearest.scatter_reduce_(1, labels[None].expand_as(d), d, "amin")  # (F, k) per individual
    out[:, ys, xs] = (nearest <= band).T
    return out


def owned_pixels(
    fg: Tensor,
    uv: Tensor,
    depth: Tensor,
    labels: Tensor,
    k: int,
    radius: float,
    reach: float,
) -> Tensor:
    """Give each foreground pixel of one view to an individual.

    A pixel goes to the nearest-in-depth individual among the voxels projecting
    within ``radius`` pixels of it, else to the individual of the nearest voxel
    within ``reach`` pixels (limbs the coarse hull lost), else to nobody.

    Args:
        fg: foreground (H, W) bool.
        uv: projections of the individuals' voxels (P, 2); depth (P,); labels (P,).
        k: number of individuals.
        radius, reach: pixels.

    Returns:
        owner map (H, W) int64 in [-1, k).
    """
    return _owners(fg.shape, *_pixel_distances(fg, uv), depth, labels, radius, reach)


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
    return _candidates(fg.shape, *_pixel_distances(fg, uv), labels, k, band)


def contested_pixels(fg: Tensor, uv: Tensor, labels: Tensor, k: int, band: float) -> Tensor:
    """The foreground pixels of one view near two or more individuals' voxels: (H, W) bool
    (arguments as :func:`candidate_individuals`)."""
    return candidate_individuals(fg, uv, labels, k, band).sum(0) >= 2


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
    occ = occupied_voxels(evidence, grid, min_views)
    idx = torch.nonzero(occ).flatten()
    owners = torch.full((V, H, W), -1, dtype=torch.long)
    candidates = torch.zeros(V, k, H, W, dtype=torch.bool)
    if len(idx) < min_voxels:
        return MultiviewProposals(boxes, depths, valid, owners, candidates)
    labels = cluster_individuals(grid.centres[idx], grid.up, grid.size, k, split=split)
    keep = labels >= 0
    idx, labels = idx[keep], labels[keep]
    f = grid.uv.new_tensor([W, H]) / 2  # pixels per normalised unit
    for v in range(V):
        vis = grid.inside[v, idx]
        z = grid.depth[v, idx[vis]]
        voxel_px = float(grid.size * grid.focal[v] / z.median()) if len(z) else 1.0
        ys, xs, d = _pixel_distances(evidence[v] > 0.5, grid.uv[v, idx[vis]])  # once for both
        owners[v] = _owners((H, W), ys, xs, d, z, labels[vis],
                            OWNER_RADIUS * voxel_px, OWNER_REACH * voxel_px)
        if contest > 0:
            candidates[v] = _candidates((H, W), ys, xs, d, labels[vis], k, contest * voxel_px)
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
