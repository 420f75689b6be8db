"""Who is who in the visual hull: its occupied voxels grouped into individuals.

The voxels that :mod:`nsd.cues.occupancy` carves are counted per column on the horizontal
plane. With the count known, a seeded k-means of the columns cuts them into individuals;
where bodies of unequal size touch (a long, low quadruped beside an upright biped), a
Gaussian mixture of the voxels in 3D replaces it, penalised for joining blobs the hull keeps
apart. As an upper bound, the heaviest connected
components are the individuals (:func:`cluster_individuals`). Through a sequence, a
:class:`ClusterTrack` hands each frame's Gaussians to the next as one more start of its
mixture (bodies move little between frames), and says whether the scene wants the mixture
at all (:func:`scene_wants_mixture`: bodies of one size keep the k-means).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from scipy import ndimage
from scipy.stats import multivariate_normal
from threadpoolctl import threadpool_limits
from torch import Tensor

from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError
from nsd.ops.vectors import up_frame

__all__ = ["ClusterTrack", "MixtureRules", "cluster_individuals", "scene_wants_mixture"]

# cluster_individuals with the count known: seeds of the k-means at least SEED_SPREAD typical
# radii apart; columns beyond GHOST_SPREAD radii of their cluster dropped. With 1.5 radii,
# hull-only detection of six huddling bipeds 0.95 -> 0.93, of the mixed group 0.62 -> 0.59
# (docs/benchmarks/hull.md); 4 was chosen on the scenes of that table.
SEED_SPREAD = 4.0
GHOST_SPREAD = 3.0
# Before those, one seed per blob (components joined across gaps of up to 2 * BLOB_GAP empty
# columns: the pieces of one carved body) that scores at least BLOB_SHARE of the mean score
# per individual, heaviest first; components of lighter blobs (ghosts) never seed. A small
# body apart from the rest (a biped beside cattle) is then an individual even where pieces of
# a big one outweigh it: hull-only detection of the seed-21 mixed group 0.69 -> 0.90, of four
# quadrupeds 0.89 -> 0.93 (docs/benchmarks/hull_blobs.md, 14 scenes). The share's plateau
# there is 0.05-0.1 (ghost blobs score <= 0.03 of the mean, lone bipeds beside cattle >= 0.06).
# On 5 scenes made after the choice (hull_blobs_blind.md) detection moved +0.11, +0.10, 0, 0
# and -0.08 (a quadruped in two blobs, both seeding); BLOB_GAP = 0: components alone.
BLOB_GAP = 1
MIN_COLUMN = 2  # voxels a column of the plane needs to count (one-voxel columns are noise)
BLOB_SHARE = 0.07
KMEANS_ITERATIONS = 10
# then a Gaussian mixture of the voxels in 3D (full covariances: a long, low quadruped beside
# upright bipeds), the best of fits from the k-means partition and from MIXTURE_RESTARTS
# k-means++ starts, replaces the k-means where the MixtureRules say so (their values and why:
# conf/inference/default.yaml).
MIXTURE_RESTARTS = 10
MIXTURE_ITERATIONS = 100
# with a track, the restarts run only where its start is less likely than the partition's by
# more than RESTART_TOLERANCE nats per voxel, what two fits of one optimum differ by (the EM's
# stopping tolerance, sklearn's default); -inf: every frame (docs/nsd.md, "A cheaper hull
# for groups")
RESTART_TOLERANCE = 1e-3
# every voxel a Gaussian holds outside its heaviest blob costs its mixture BLOB_PENALTY nats,
# spread over the voxels: two small bodies apart cost one Gaussian little likelihood, a big
# body in two gains much. Hull-only detection over the whole recording: +0.031-0.051 on four
# huddles of both species, +0.005-0.041 on four scenes made after the choice, none of 25
# scenes lower by more than 0.001 (docs/benchmarks/hull_blob_penalty.md); 3 lost 0.06 on one
# scene; 0: off
BLOB_PENALTY = 2.0


@dataclass(frozen=True)
class MixtureRules(ConfigSection):
    """When the hull's 3D Gaussian mixture replaces its k-means (the ``mixture_*`` keys of
    the ``inference`` block, shared by training's hull proposals; defaults and the
    measurements behind them: conf/inference/default.yaml).

    Attributes:
        mixture_gain: the mixture's labels replace the k-means' where it explains the
            voxels better than Gaussians fitted to the k-means partition by at least this
            many nats per voxel (``inf``: never; ``-inf``: always, whatever the scene).
        mixture_slack: through a sequence, the mixture started from the previous frame's
            Gaussians is kept unless another start is better by more than this (nats per
            voxel; ``-inf``: each frame alone).
        mixture_scene_gain: per scene, the mixture is tried only where the median of its
            gains at ``mixture_scene_sample`` instants spread over the scene reaches this
            (nats per voxel; ``-inf``: every scene).
        mixture_scene_sample: instants read for that decision (>= 1).
    """

    APP: ClassVar[str] = "train"  # defaults: conf/train.yaml, section `inference`
    KEY: ClassVar[str] = "inference"

    mixture_gain: float
    mixture_slack: float
    mixture_scene_gain: float
    mixture_scene_sample: int

    def validate(self) -> None:
        for key in ("mixture_gain", "mixture_slack", "mixture_scene_gain"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float) or value != value:
                raise ConfigError(f"inference.{key} must be a number (nats per voxel; inf and "
                                  f"-inf allowed), got {value!r}")
        n = self.mixture_scene_sample
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"inference.mixture_scene_sample must be a whole number of "
                              f"instants >= 1, got {n!r}")


@dataclass
class ClusterTrack:
    """What one frame's clustering hands to the next (:func:`cluster_individuals`).

    Attributes:
        weights: (k,) the Gaussians' shares of the voxels, None before the first frame
            (or after one that could not fit k Gaussians).
        means: (k, 3).
        precisions: (k, 3, 3) inverse covariances.
        mixture: whether the 3D mixture may replace the k-means in this scene
            (:func:`scene_wants_mixture`); False: the k-means alone, nothing fitted.
        gains: the mixture's gain over the k-means partition (nats per voxel) at each
            frame so far where it was fitted.
        rules: when the mixture replaces the k-means (None: the shipped defaults).
    """

    weights: np.ndarray | None = None
    means: np.ndarray | None = None
    precisions: np.ndarray | None = None
    mixture: bool = True
    gains: list[float] = field(default_factory=list)
    rules: MixtureRules | None = None

    def __post_init__(self) -> None:
        if self.rules is None:
            self.rules = MixtureRules.defaults()

    def keep(self, weights: np.ndarray | None, means: np.ndarray | None = None,
             precisions: np.ndarray | None = None) -> None:
        """Hand these Gaussians (None: none) to the next frame."""
        self.weights, self.means, self.precisions = weights, means, precisions


def scene_wants_mixture(gains: list[float], scene_gain: float) -> bool:
    """Whether a scene's hull should try the 3D mixture, from its gains (nats per voxel)
    at instants spread over the scene (a ``ClusterTrack``'s ``gains``): their median
    reaches ``scene_gain`` (``MixtureRules.mixture_scene_gain``), or there are none (every
    instant's bodies apart: nothing to judge, each instant decides).

    Example:
        >>> scene_wants_mixture([0.0, 0.12, -0.01], 0.03)
        False
        >>> scene_wants_mixture([0.1, 0.02, 0.08], 0.03)
        True
    """
    return not gains or float(np.median(gains)) >= scene_gain


def _stable_rank(centres: np.ndarray) -> np.ndarray:
    """(k,) the rank of each of the ``k`` cluster centres (k, 2) along the first plane
    axis: labels in a stable order from frame to frame."""
    rank = np.empty(len(centres), np.int64)
    rank[np.argsort(centres[:, 0], kind="stable")] = np.arange(len(centres))
    return rank


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


def _blob_seeds(w: np.ndarray, comp: np.ndarray, n: int, blob: np.ndarray, order: np.ndarray,
                k: int) -> tuple[list[int], np.ndarray]:
    """The components (indices in [0, n)) that seed the individuals first, and (n,) bool:
    the components that may seed at all. Columns: weights ``w`` (C,), components ``comp``
    (C,), blobs ``blob`` (C,); ``order``: the components by decreasing score. A blob seeds
    when it scores at least ``BLOB_SHARE`` of the mean score per individual (the total over
    ``k``; the heaviest blob always): its heaviest component, blobs by decreasing score, at
    most ``k``. A component of a lighter blob (a ghost) never seeds."""
    score = np.bincount(blob, weights=w)
    of = np.zeros(n, np.int64)
    of[comp] = blob  # each component's blob (a component lies in one blob)
    live = (score[of] >= BLOB_SHARE * score.sum() / k) | (of == np.argmax(score))
    first: dict[int, int] = {}
    for c in order:
        first.setdefault(int(of[c]), int(c))
    blobs = [b for b in np.argsort(-score, kind="stable")[:k] if live[first[int(b)]]]
    return [first[int(b)] for b in blobs], live


def _seeded_columns(cxy: np.ndarray, w: np.ndarray, comp: np.ndarray, n: int, k: int,
                    cell: float, blob: np.ndarray | None = None) -> np.ndarray:
    """Labels (C,) in [0, k) or -1 of the plane's columns (centres ``cxy`` (C, 2), weights
    ``w`` (C,), components ``comp`` (C,) in [0, n), blobs ``blob`` (C,) or None) for ``k``
    individuals (see :func:`cluster_individuals`)."""
    score = np.bincount(comp, weights=w, minlength=n)
    centre = np.stack([np.average(cxy[comp == c], axis=0, weights=w[comp == c])
                       for c in range(n)])
    rms = np.array([_weighted_rms(cxy[comp == c], centre[c], w[comp == c], cell)
                    for c in range(n)])
    order = np.argsort(-score)
    apart = SEED_SPREAD * float(np.median(rms[order[:k]]))
    seeds, live = [], np.ones(n, bool)
    if blob is not None:
        seeds, live = _blob_seeds(w, comp, n, blob, order, k)
    for c in order:
        if len(seeds) == k:
            break
        if live[c] and c not in seeds and all(
                np.linalg.norm(centre[c] - centre[s]) >= apart for s in seeds):
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
    return np.where(lab >= 0, _stable_rank(centres)[lab], -1)


def _partition_gaussians(x: np.ndarray, labels: np.ndarray, k: int,
                         reg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Gaussians fitted to the hard partition ``labels`` (P,) in [0, k) of ``x`` (P, D):
    weights by size (k,), means (k, D) and covariances plus ``reg`` on the diagonal
    (k, D, D); parts of at most D points are left out (fewer than ``k`` rows)."""
    parts = [j for j in range(k) if (labels == j).sum() > x.shape[1]]
    weights = np.array([(labels == j).mean() for j in parts])
    means = np.array([x[labels == j].mean(0) for j in parts]).reshape(len(parts), x.shape[1])
    covs = np.array([np.cov(x[labels == j].T) + reg * np.eye(x.shape[1]) for j in parts])
    return weights, means, covs.reshape(len(parts), x.shape[1], x.shape[1])


def _partition_loglik(x: np.ndarray, labels: np.ndarray, k: int, reg: float) -> float:
    """Mean log-likelihood (nats per point) of ``x`` (P, D) under the Gaussian mixture
    fitted to the hard partition ``labels`` (P,) in [0, k) (:func:`_partition_gaussians`)."""
    weights, means, covs = _partition_gaussians(x, labels, k, reg)
    logp = [np.log(w) + multivariate_normal(m, c).logpdf(x)
            for w, m, c in zip(weights, means, covs, strict=True)]
    return float(np.logaddexp.reduce(np.stack(logp), axis=0).mean()) if logp else -np.inf


def _spanning_share(labels: np.ndarray, blobs: np.ndarray | None, k: int) -> float:
    """The share of the points whose label (P,) in [0, k) holds more points in another of
    the ``blobs`` (P,) >= 0 than in theirs: what a partition joins that the hull keeps
    apart (0 without blobs)."""
    if blobs is None or not len(labels):
        return 0.0
    held = np.zeros((k, int(blobs.max()) + 1))
    np.add.at(held, (labels, blobs), 1)
    return 1.0 - float(held.max(1).sum()) / len(labels)


def _blob_means(x: np.ndarray, blobs: np.ndarray, k: int) -> np.ndarray:
    """(k, D) starts of a mixture of ``x`` (P, D): the means of the ``k`` heaviest of the
    ``blobs`` (P,) >= 0; while fewer, the heaviest part cut in two across its principal axis
    at its mean."""
    count = np.bincount(blobs)
    parts = [x[blobs == b] for b in np.argsort(-count, kind="stable")[:k] if count[b]]
    while len(parts) < k:
        j = int(np.argmax([len(p) for p in parts]))
        part = parts.pop(j)
        if len(part) < 2:  # nothing to cut: the same start twice
            parts += [part, part]
            continue
        axis = np.linalg.eigh(np.cov(part.T))[1][:, -1]
        side = (part - part.mean(0)) @ axis > 0
        parts += [part[side], part[~side]] if side.any() and (~side).any() else [part, part]
    return np.stack([p.mean(0) for p in parts])


def _hand_partition(track: ClusterTrack, x: np.ndarray, labels: np.ndarray, k: int,
                    reg: float) -> None:
    """Hand the ``track`` the Gaussians of the partition ``labels`` (P,) in [0, k) or -1 of
    ``x`` (P, D) (:func:`_partition_gaussians` of the kept points), none if a part is too
    small for one."""
    keep = labels >= 0
    weights, means, covs = _partition_gaussians(x[keep], labels[keep], k, reg)
    if len(weights) < k:
        track.keep(None)
    else:
        track.keep(weights, means, np.linalg.inv(covs))


def _mixture_labels(x: np.ndarray, labels: np.ndarray, k: int, reg: float, gain: float,
                    track: ClusterTrack, blobs: np.ndarray | None = None) -> np.ndarray | None:
    """Labels (P,) in [0, k) of ``x`` (P, D) by a Gaussian mixture (full covariances,
    ``reg`` added to them), or None where it does not explain ``x`` better than the
    partition ``labels`` (P,) in [0, k) does (:func:`_partition_loglik`).

    The best of the mixtures started from the partition, from the ``blobs`` (P,) >= 0 (one
    Gaussian per blob, :func:`_blob_means`; None: no blobs), from ``MIXTURE_RESTARTS``
    k-means++ seeds and from the ``track``'s Gaussians (kept unless another is better by
    more than its rules' ``mixture_slack``) must gain ``gain`` nats per point; the gain is
    added to the ``track``'s. Every fit, and the partition, is scored by its log-likelihood
    less ``BLOB_PENALTY`` times the share of points its labels hold outside their heaviest
    blob (:func:`_spanning_share`): two small bodies the hull keeps apart are not one
    Gaussian so that a big body can take two. The ``track`` is handed the kept mixture, or
    the partition's Gaussians where the mixture is not kept. Where the track's start is as
    likely as the partition's and the blobs' (within ``RESTART_TOLERANCE``) or more, the
    bodies are where the last frame left them and the restarts are not run (docs/nsd.md,
    "A cheaper hull for groups").
    """
    # lazy: scikit-learn (1.9 s to import) only where the hull's k-means may have cut a body
    from sklearn.mixture import GaussianMixture

    def fit(**start) -> GaussianMixture:
        return GaussianMixture(k, covariance_type="full", reg_covar=reg,
                               max_iter=MIXTURE_ITERATIONS, **start).fit(x)

    predicted: dict[int, np.ndarray] = {}  # each fit's labels, computed once

    def score(g: GaussianMixture) -> float:  # nats per point, the blob penalty taken off
        predicted[id(g)] = g.predict(x)
        return g.score(x) - BLOB_PENALTY * _spanning_share(predicted[id(g)], blobs, k)

    # one BLAS thread: on these small matrices, threads contending with torch's idle ones
    # made a held-out frame of the default scene's hull 0.10 s instead of 0.04
    with threadpool_limits(1):
        base = (_partition_loglik(x, labels, k, reg)
                - BLOB_PENALTY * _spanning_share(labels, blobs, k))
        means = np.stack([x[labels == j].mean(0) if (labels == j).any() else x.mean(0)
                          for j in range(k)])
        fits = [fit(means_init=means, random_state=0)]
        if blobs is not None:  # one more start: a Gaussian per blob, the heaviest split
            fits.append(fit(means_init=_blob_means(x, blobs, k), random_state=0))
        scores = [score(g) for g in fits]
        carried = None
        if track.weights is not None:
            carried = fit(weights_init=track.weights, means_init=track.means,
                          precisions_init=track.precisions, random_state=0)
            carried_score = score(carried)
        # no track, or it may have lost a body
        if carried is None or carried_score < max(scores) - RESTART_TOLERANCE:
            restarts = [fit(init_params="k-means++", random_state=s)
                        for s in range(MIXTURE_RESTARTS)]
            fits += restarts
            scores += [score(g) for g in restarts]
        best = int(np.argmax(scores))
        if carried is not None:
            fits.append(carried)
            scores.append(carried_score)
            if carried_score >= scores[best] - track.rules.mixture_slack:
                best = len(fits) - 1
        track.gains.append(float(scores[best] - base))
        if track.gains[-1] < gain:
            _hand_partition(track, x, labels, k, reg)
            return None
        kept = fits[best]
        track.keep(kept.weights_, kept.means_, kept.precisions_)
        return predicted[id(kept)]


def _mixture_relabelled(x: np.ndarray, plane: np.ndarray, labels: np.ndarray, k: int,
                        reg: float, gain: float, track: ClusterTrack,
                        blobs: np.ndarray | None = None) -> np.ndarray:
    """``labels`` (P,) in [0, k) or -1 of the points ``x`` (P, 3) (``plane`` (P, 2): their
    ground-plane coordinates) with the kept ones (>= 0) replaced by the mixture's
    (:func:`_mixture_labels`, which updates the ``track``), ranked along the first plane
    axis; unchanged where the mixture does not gain ``gain`` or the partition has fewer
    than ``k`` parts."""
    keep = labels >= 0
    if len(np.unique(labels[keep])) < k or keep.sum() <= 4 * k:
        return labels
    mixed = _mixture_labels(x[keep], labels[keep], k, reg, gain, track,
                            None if blobs is None else blobs[keep])
    if mixed is None:
        return labels
    kept = plane[keep]
    centres = np.stack([kept[mixed == j].mean(0) if (mixed == j).any()
                        else np.full(2, np.inf) for j in range(k)])
    out = labels.copy()
    out[keep] = _stable_rank(centres)[mixed]
    return out


def cluster_individuals(
    points: Tensor,
    up: Tensor,
    cell: float,
    k: int,
    min_column: int = MIN_COLUMN,
    split: bool = True,
    ghost_ratio: float = 0.2,
    mixture_gain: float | None = None,
    track: ClusterTrack | None = None,
) -> Tensor:
    """Individual labels (P,) in [0, k) or -1 (dropped) for occupied voxel centres (P, 3).

    Columns of the horizontal plane (side ``cell``) holding at least ``min_column``
    voxels are grouped into 4-connected components, weighted by their squared column
    heights (tall bodies over low ghosts).

    With ``split`` (``k`` is the number of individuals), the components seed a weighted
    k-means of the columns. First the blobs (components joined across gaps of up to
    ``2 * BLOB_GAP`` empty columns) that score at least ``BLOB_SHARE`` of the mean score per
    individual give one seed each, their heaviest component, heaviest blob first: a small
    body apart from the others is an individual even where pieces of a big body outweigh
    it. Then the heaviest components of such blobs whose centres lie at least
    ``SEED_SPREAD`` typical radii apart (the median weighted RMS radius of the ``k``
    heaviest components: the scale of an individual in this scene, whatever its units or
    species) from every seed are seeds; while there are fewer than ``k``, the heaviest
    cluster is cut in two along its principal axis; k-means then moves the ``k`` centres
    and every column goes to the nearest. The pieces an individual's hull falls into (legs
    apart, a thin waist) join their body instead of taking the slot of an individual merged
    with another, and a huddle is cut where the columns' mass says. Columns farther than
    ``GHOST_SPREAD`` times their cluster's RMS radius from its centre are dropped (ghosts).
    The k-means assumes bodies of one size. Unless each cluster is one whole component
    (individuals apart), where a Gaussian mixture of the kept voxels in 3D explains them
    better by ``mixture_gain`` nats per voxel (None: the ``track``'s rules', or the shipped
    default without a track; ``inf``: never; ``-inf``: always), its labels replace the
    k-means': a long quadruped is not cut at the midpoint to an upright neighbour. The
    mixture pays for every voxel a Gaussian holds outside its heaviest blob
    (``BLOB_PENALTY``): it does not join two small bodies the hull keeps apart to cut a
    big one in two. A ``track`` carried through a sequence of frames starts one more
    mixture from the previous frame's Gaussians and prefers it unless another start is
    better by more than its rules' ``mixture_slack``; it is handed this frame's Gaussians
    (the kept mixture's, or the k-means partition's) and its gain. A track whose
    ``mixture`` is False (a scene of bodies of one size, :func:`scene_wants_mixture`)
    keeps the k-means and fits nothing, unless ``mixture_gain`` is ``-inf``.

    Without (``k`` is only an upper bound), the ``k`` heaviest components are the
    individuals, nothing is split and components scoring below ``ghost_ratio`` times the
    heaviest are dropped as ghosts: the labels then say how many individuals the hull
    holds, instead of cutting one individual into ``k`` parts.
    """

    xy = points @ up_frame(up)[:, :2]  # (P, 2): coordinates in the plane orthogonal to up
    ij = torch.floor((xy - xy.min(0).values) / cell).long()
    shape = (int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1)
    cols = (ij[:, 0].numpy(), ij[:, 1].numpy())  # each point's column
    counts = np.zeros(shape)
    np.add.at(counts, cols, 1)
    # thin columns (one voxel) are hull noise and bridge neighbours: drop them
    kept = counts >= min_column
    comp, n = ndimage.label(kept)
    labels = torch.full((len(points),), -1, dtype=torch.long)
    if n == 0:
        return labels
    if split:
        column = np.full(shape, -1, np.int64)
        blob = (ndimage.label(ndimage.binary_dilation(kept, iterations=BLOB_GAP))[0][kept] - 1
                if BLOB_GAP else None)
        blob_of = np.zeros(shape, np.int64)  # each kept column's blob (components: no gap)
        blob_of[kept] = comp[kept] - 1 if blob is None else blob
        column[kept] = _seeded_columns((np.argwhere(kept) + 0.5) * cell, counts[kept] ** 2,
                                       comp[kept] - 1, n, k, cell, blob)
        labels = column[cols]
        carried = ClusterTrack() if track is None else track
        gain = carried.rules.mixture_gain if mixture_gain is None else mixture_gain
        pairs = np.unique(np.stack([comp[kept], column[kept]], 1)[column[kept] >= 0], axis=0)
        # each individual one whole component (apart): nothing for the mixture to mend
        whole = len(pairs) == k and len(np.unique(pairs[:, 0])) == k
        x = points.double().numpy()
        tried = track is None or track.mixture or gain == -np.inf
        if gain < np.inf and (not whole or gain == -np.inf) and tried:
            labels = _mixture_relabelled(x, xy.double().numpy(), labels, k, cell**2, gain,
                                         carried, blob_of[cols])
        elif track is not None:  # nothing fitted: the partition's Gaussians, for the next
            _hand_partition(track, x, labels, k, cell**2)
        return torch.as_tensor(labels)
    point_comp = torch.as_tensor(comp[cols]) - 1  # (P,)
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
