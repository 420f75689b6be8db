"""The hull's individuals: the k-means of the plane's columns and the 3D mixture that
replaces it where bodies of unequal size touch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nsd.core.errors import ConfigError
from nsd.cues import clustering, occupancy
from nsd.cues.clustering import (
    ClusterTrack,
    MixtureRules,
    _blob_means,
    _mixture_labels,
    _partition_gaussians,
    _partition_loglik,
    _spanning_share,
    cluster_individuals,
)


def _columns(centres_xy, radius: float, height: int, cell: float) -> torch.Tensor:
    """Voxel centres (P, 3) of round bodies: columns of ``height`` voxels within ``radius``
    of each (x, y) centre, z up."""
    pts = []
    for cx, cy in centres_xy:
        for i in np.arange(-radius, radius + cell / 2, cell):
            for j in np.arange(-radius, radius + cell / 2, cell):
                if i * i + j * j <= radius * radius:
                    pts += [(cx + i, cy + j, (h + 0.5) * cell) for h in range(height)]
    return torch.tensor(pts, dtype=torch.float32)


def test_pieces_of_one_individual_join_it_instead_of_taking_a_slot():
    """Three bodies, one of them broken in two pieces by a gap in the hull (legs apart):
    with k = 3 the pieces are one individual and the other two keep their own labels;
    the old rule (the k heaviest components) gave the two pieces two slots and merged
    nobody else, so one body lost its label."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    whole = _columns([(0.0, 0.0), (1.5, 0.0)], 0.25, 16, cell)
    pieces = _columns([(-1.5, 0.2), (-1.5, -0.2)], 0.12, 14, cell)  # 0.16 m gap between
    labels = cluster_individuals(torch.cat([whole, pieces]), up, cell, 3)
    n = len(whole) // 2
    a, b, broken = labels[:n], labels[n : 2 * n], labels[2 * n :]
    assert len(set(broken.tolist())) == 1 and broken[0] >= 0
    assert len(set(a.tolist())) == 1 and len(set(b.tolist())) == 1
    assert len({int(a[0]), int(b[0]), int(broken[0])}) == 3


def test_a_huddle_of_three_in_one_component_is_cut_into_three():
    """Three bodies in a row whose hulls touch (one plane component): k = 3 gives each its
    own label; ``split=False`` (k an upper bound) keeps them as one."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    bodies = [(-0.4, 0.0), (0.0, 0.0), (0.4, 0.0)]
    pts = _columns(bodies, 0.25, 16, cell)
    labels = cluster_individuals(pts, up, cell, 3)
    xy = pts[:, :2]
    nearest = torch.cdist(xy, torch.tensor(bodies)).argmin(1)
    for j in range(3):  # each body's columns (away from the seams) carry one label
        core = (nearest == j) & (torch.cdist(xy, torch.tensor(bodies))[:, j] < 0.15)
        assert len(set(labels[core].tolist())) == 1
    assert len(set(labels.tolist()) - {-1}) == 3
    assert set(cluster_individuals(pts, up, cell, 3, split=False).tolist()) == {0}


def _ellipse_columns(centre, semi: tuple[float, float], height: int, cell: float) -> torch.Tensor:
    """Voxel centres (P, 3) of a long, low body: columns of ``height`` voxels inside the
    ellipse of semi-axes ``semi`` (along x, y) around ``centre``, z up."""
    a, b = semi
    pts = [(centre[0] + i, centre[1] + j, (h + 0.5) * cell)
           for i in np.arange(-a, a + cell / 2, cell) for j in np.arange(-b, b + cell / 2, cell)
           if (i / a) ** 2 + (j / b) ** 2 <= 1 for h in range(height)]
    return torch.tensor(pts, dtype=torch.float32)


def _long_beside_round(cell: float) -> tuple[torch.Tensor, int]:
    """Voxel centres (P, 3) of a long, low body at the origin beside a round, upright one
    1.3 to its side, and how many of them (the first) are the long body's."""
    long_body = _ellipse_columns((0.0, 0.0), (0.8, 0.25), 6, cell)
    return torch.cat([long_body, _columns([(1.3, 0.0)], 0.25, 16, cell)]), len(long_body)


def test_a_long_low_body_beside_an_upright_one_is_not_cut_at_the_midpoint():
    """A quadruped-like body (1.6 m long, 0.6 m high) with an upright one 0.25 m beyond its
    nose: the k-means of the columns gives the nose to the upright body (it lies nearer
    that centre); the 3D mixture keeps each body whole."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    long_body = _ellipse_columns((0.0, 0.0), (0.8, 0.25), 6, cell)
    upright = _columns([(1.3, 0.0)], 0.25, 16, cell)
    pts = torch.cat([long_body, upright])
    n = len(long_body)
    kmeans = cluster_individuals(pts, up, cell, 2, mixture_gain=np.inf)
    assert len(set(kmeans[:n].tolist())) == 2  # the k-means cuts the long body
    labels = cluster_individuals(pts, up, cell, 2)
    assert set(labels[:n].tolist()) == {0} and set(labels[n:].tolist()) == {1}


def test_equal_bodies_keep_the_k_means_labels():
    """Three equal bodies in a row (one component): the mixture gains nothing over the
    k-means partition, so the labels are the k-means'; forced (``-inf``), it labels the
    same voxels (no voxel dropped or added) with three labels in a stable order."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    pts = _columns([(-0.4, 0.0), (0.0, 0.0), (0.4, 0.0)], 0.25, 16, cell)
    kmeans = cluster_individuals(pts, up, cell, 3, mixture_gain=np.inf)
    assert torch.equal(cluster_individuals(pts, up, cell, 3), kmeans)
    forced = cluster_individuals(pts, up, cell, 3, mixture_gain=-np.inf)
    assert torch.equal(forced >= 0, kmeans >= 0)
    x = pts[:, 0]
    assert [float(x[forced == j].mean()) for j in range(3)] == sorted(
        float(x[forced == j].mean()) for j in range(3))


def _carved(centre, semi: tuple[float, float], height: int, cell: float,
            gaps: tuple[float, ...]) -> torch.Tensor:
    """A long, low body (:func:`_ellipse_columns`) carved into pieces: the columns within
    half a cell of each ``gaps`` x offset from its centre removed."""
    pts = _ellipse_columns(centre, semi, height, cell)
    cut = torch.zeros(len(pts), dtype=torch.bool)
    for g in gaps:
        cut |= (pts[:, 0] - centre[0] - g).abs() < cell / 2
    return pts[~cut]


def _labels_per_body(labels: torch.Tensor, bodies: list[torch.Tensor]) -> list[set[int]]:
    """The set of labels each body's voxels (consecutive in ``labels``) carry."""
    out, i = [], 0
    for b in bodies:
        out.append(set(labels[i : i + len(b)].tolist()))
        i += len(b)
    return out


def test_a_small_body_apart_keeps_its_label_where_pieces_of_big_ones_outweigh_it(monkeypatch):
    """Two long, low bodies, each carved into four pieces by one-column gaps, and two
    small upright bodies 0.7 apart beyond them (bipeds beside cattle whose hull fell apart):
    with k = 4 every body is one individual of its own. Seeded by components alone
    (``BLOB_GAP = 0``, the rule before), the heavier pieces take the seeds: the big bodies
    are cut and the two small ones share a label."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    bodies = [_carved((0.0, cy), (1.0, 0.3), 8, cell, (-0.5, 0.0, 0.5)) for cy in (0.0, -1.2)]
    bodies += [_columns([(x, 1.6)], 0.1, 10, cell) for x in (-0.35, 0.35)]
    pts = torch.cat(bodies)
    for gain in (np.inf, None):  # the k-means alone, and with the mixture's rule
        per_body = _labels_per_body(cluster_individuals(pts, up, cell, 4, mixture_gain=gain),
                                    bodies)
        assert all(len(b) == 1 for b in per_body)
        assert set.union(*per_body) == {0, 1, 2, 3}
    monkeypatch.setattr(clustering, "BLOB_GAP", 0)
    before = _labels_per_body(cluster_individuals(pts, up, cell, 4, mixture_gain=np.inf),
                              bodies)
    assert before[2] == before[3]  # the two small bodies merged
    assert len(before[0]) > 1  # and a big one cut


def test_a_ghost_blob_takes_no_seed_from_a_huddle(monkeypatch):
    """A huddle of three (one component) and, far from it, one column of two voxels (a
    ghost of the hull, 0.03 % of the score): the huddle is cut into three and the ghost
    dropped. Were every blob a seed (``BLOB_SHARE = 0``), the ghost would take a slot and
    the huddle be cut in two only."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    huddle = _columns([(-0.4, 0.0), (0.0, 0.0), (0.4, 0.0)], 0.25, 16, cell)
    ghost = torch.tensor([[2.0, 2.0, 0.05], [2.0, 2.0, 0.15]])
    pts = torch.cat([huddle, ghost])
    labels = cluster_individuals(pts, up, cell, 3)
    assert set(labels[: len(huddle)].tolist()) == {0, 1, 2}
    assert set(labels[len(huddle) :].tolist()) == {-1}
    monkeypatch.setattr(clustering, "BLOB_SHARE", 0.0)
    every = cluster_individuals(pts, up, cell, 3)
    assert len(set(every[: len(huddle)].tolist())) == 2
    assert set(every[len(huddle) :].tolist()) == {int(every[-1])} and int(every[-1]) >= 0


def test_blob_seeds_known_values():
    """Five components in three blobs (column weights below): blob 0 (components 0, 1)
    scores 10, blob 1 (component 2) 6, blob 2 (components 3, 4) 0.5; the mean per individual
    with k = 3 is 16.5 / 3 = 5.5, so the floor at 0.07 is 0.385: blobs 0 and 1 seed with
    their heaviest components (0 and 2), blob 2 too (0.5 >= 0.385) with component 4. With
    k = 2 the floor is 0.58: blob 2 is a ghost and neither of its components may seed."""
    w = np.array([4.0, 3.0, 3.0, 6.0, 0.2, 0.3])
    comp = np.array([0, 0, 1, 2, 3, 4])
    blob = np.array([0, 0, 0, 1, 2, 2])
    order = np.argsort(-np.bincount(comp, weights=w))  # components by score: 0, 2, 1, 4, 3
    seeds, live = clustering._blob_seeds(w, comp, 5, blob, order, 3)
    assert seeds == [0, 2, 4] and live.all()
    seeds, live = clustering._blob_seeds(w, comp, 5, blob, order, 2)
    assert seeds == [0, 2] and live.tolist() == [True, True, True, False, False]


def test_partition_loglik_matches_a_slow_reference():
    """The partition's mixture log-likelihood against the Gaussian density written out
    point by point."""
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(0, 1, (40, 3)), rng.normal(3, 0.5, (25, 3))])
    labels = np.repeat([0, 1], [40, 25])
    reg = 0.01
    parts = []
    for j in (0, 1):
        xj = x[labels == j]
        mu = xj.mean(0)
        cov = (xj - mu).T @ (xj - mu) / (len(xj) - 1) + reg * np.eye(3)
        parts.append((len(xj) / len(x), mu, cov))
    ref = 0.0
    for p in x:
        dens = sum(w * np.exp(-0.5 * (p - mu) @ np.linalg.solve(cov, p - mu))
                   / np.sqrt((2 * np.pi) ** 3 * np.linalg.det(cov)) for w, mu, cov in parts)
        ref += np.log(dens) / len(x)
    assert _partition_loglik(x, labels, 2, reg) == pytest.approx(ref, rel=1e-10)


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Two labellings (P,) split the points alike (whatever the label numbers)."""
    return len(np.unique(np.stack([a, b], 1), axis=0)) == len(np.unique(a)) == len(np.unique(b))


def test_a_track_keeps_the_previous_frames_partition_where_two_are_as_likely():
    """Four blobs at the corners of a square and two individuals: left | right and
    top | bottom explain the points equally well (by symmetry), both far better than the
    diagonal pairs the k-means gave. Carried from a frame that had either, the track
    keeps it; it is handed the kept mixture."""
    rng = np.random.default_rng(1)
    corners = np.array([(-1, -1, 0), (-1, 1, 0), (1, -1, 0), (1, 1, 0)], float)
    x = np.concatenate([c + rng.normal(0, 0.2, (150, 3)) for c in corners])
    corner = np.repeat(np.arange(4), 150)
    diagonal = np.isin(corner, (0, 3)).astype(int)
    reg = 1e-3
    for side in (corner // 2, corner % 2):  # left | right, then bottom | top
        weights, means, covs = _partition_gaussians(x, side, 2, reg)
        track = ClusterTrack(weights, means, np.linalg.inv(covs))
        labels = _mixture_labels(x, diagonal, 2, reg, 0.02, track)
        assert labels is not None and _same_partition(labels, side)
        assert np.allclose(np.sort(track.means[:, :2], 0), np.sort(means[:, :2], 0), atol=0.05)


def test_a_track_is_handed_the_partition_where_the_k_means_is_kept():
    """Two bodies apart (each one whole component): the k-means' labels stand, and the
    track is handed their Gaussians: each body's mean and the inverse of its covariance
    (plus the voxel side squared)."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    pts = _columns([(-1.0, 0.0), (1.0, 0.0)], 0.25, 16, cell)
    track = ClusterTrack()
    labels = cluster_individuals(pts, up, cell, 2, track=track).numpy()
    x = pts.double().numpy()
    order = np.argsort(track.means[:, 0])
    for j, body in enumerate((x[:, 0] < 0, x[:, 0] > 0)):
        assert len(set(labels[body].tolist())) == 1
        mean = track.means[order[j]]
        assert np.allclose(mean, x[body].mean(0))
        cov = np.cov(x[body].T) + cell**2 * np.eye(3)
        assert np.allclose(track.precisions[order[j]] @ cov, np.eye(3), atol=1e-8)
    assert np.allclose(np.sort(track.weights), [0.5, 0.5])


def test_a_scene_without_the_mixture_keeps_the_k_means_and_fits_nothing():
    """The long body beside the upright one: a track of a scene whose mixture gains little
    (``mixture=False``) keeps the k-means labels, records no gain and is handed the
    k-means' Gaussians; a track of a scene that wants it gets the mixture's labels and this
    frame's gain; forced (``-inf``), the mixture is fitted whatever the scene."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    pts, n = _long_beside_round(cell)
    kmeans = cluster_individuals(pts, up, cell, 2, mixture_gain=np.inf)
    quiet = ClusterTrack(mixture=False)
    assert torch.equal(cluster_individuals(pts, up, cell, 2, track=quiet), kmeans)
    assert quiet.gains == []
    parts = _partition_gaussians(pts.double().numpy(), kmeans.numpy(), 2, cell**2)[1]
    assert np.allclose(np.sort(quiet.means[:, 0]), np.sort(parts[:, 0]))
    for track, mixture_gain in ((ClusterTrack(), None),
                                (ClusterTrack(mixture=False), -np.inf)):
        labels = cluster_individuals(pts, up, cell, 2, mixture_gain=mixture_gain, track=track)
        assert set(labels[:n].tolist()) == {0} and set(labels[n:].tolist()) == {1}
        assert len(track.gains) == 1 and track.gains[0] > track.rules.mixture_scene_gain


def test_scene_track_decides_from_instants_spread_over_the_scene(monkeypatch):
    """``scene_track`` reads ``mixture_scene_sample`` instants spread evenly from first to
    last and turns the mixture off where their median gain is below
    ``mixture_scene_gain``; the track it returns carries its rules; without ``split`` it
    reads nothing."""
    read, gains = [], iter([0.0, 0.2, -0.01, 0.01] * 10)

    def hull(ev, grid, k, min_views=None, track=None):
        read.append(int(ev))
        track.gains.append(next(gains))
        return None, None

    monkeypatch.setattr(occupancy, "hull_individuals", hull)
    instants = list(range(100, 400, 3))  # 100 instants
    track = occupancy.scene_track(torch.tensor, instants, None, 2)
    assert len(read) == track.rules.mixture_scene_sample == 12
    assert read[0] == 100 and read[-1] == 397
    assert np.all(np.diff(read) > 0) and not track.mixture and track.gains == []
    # what it decided from: the gains of the instants read, in order
    gains, read = iter([0.0, 0.2, -0.01, 0.01] * 10), []
    assert occupancy.scene_gains(torch.tensor, instants, None, 2) == [0.0, 0.2, -0.01, 0.01] * 3
    assert len(read) == 12
    gains = iter([0.05, 0.2, 0.01] * 10)
    assert occupancy.scene_track(torch.tensor, instants, None, 2).mixture
    read.clear()
    assert occupancy.scene_track(torch.tensor, instants, None, 2, split=False).mixture
    assert read == []
    # other rules: 5 instants, a median gain of 0.01 is enough where the bar is 0.005
    rules = MixtureRules.defaults(mixture_scene_sample=5, mixture_scene_gain=0.005)
    gains = iter([0.0, 0.2, -0.01, 0.01, 0.01])
    track = occupancy.scene_track(torch.tensor, instants, None, 2, rules=rules)
    assert read == [100, 175, 250, 322, 397] and track.mixture and track.rules == rules


def test_a_track_s_rules_decide_the_mixture_of_each_frame():
    """The ``mixture_gain`` of a track's rules is the bar of each frame: ``inf`` keeps the
    k-means and fits nothing, the shipped bar takes the mixture where a long body beside a
    round one gains more, ``-inf`` takes it whatever the gain."""
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    pts, _ = _long_beside_round(cell)
    kmeans = cluster_individuals(pts, up, cell, 2, mixture_gain=np.inf)
    never = ClusterTrack(rules=MixtureRules.defaults(mixture_gain=np.inf))
    assert torch.equal(cluster_individuals(pts, up, cell, 2, track=never), kmeans)
    assert never.gains == []
    shipped = ClusterTrack()
    mixed = cluster_individuals(pts, up, cell, 2, track=shipped)
    assert not torch.equal(mixed, kmeans)
    gain = shipped.gains[0]
    above = ClusterTrack(rules=MixtureRules.defaults(mixture_gain=gain + 1e-6))
    assert torch.equal(cluster_individuals(pts, up, cell, 2, track=above), kmeans)
    below = ClusterTrack(rules=MixtureRules.defaults(mixture_gain=gain - 1e-6))
    assert torch.equal(cluster_individuals(pts, up, cell, 2, track=below), mixed)


@pytest.mark.parametrize("key, value", [("mixture_gain", float("nan")), ("mixture_slack", "x"),
                                        ("mixture_scene_sample", 0),
                                        ("mixture_scene_sample", 2.5)])
def test_mixture_rules_name_a_bad_key(key, value):
    with pytest.raises(ConfigError, match=rf"inference\.{key}"):
        MixtureRules.defaults(**{key: value})


def test_the_restarts_run_only_where_the_track_may_have_lost_a_body(monkeypatch):
    """A long body beside a round one. The first frame has no track: the partition's start
    and ``MIXTURE_RESTARTS`` k-means++ starts are fitted. The next frame, the same bodies:
    the track's start is at least as likely as the partition's, so only those two are
    fitted, and the labels stay. Once the bodies have moved far from the track's
    Gaussians, its start is the less likely one and the restarts run again; the labels
    still follow the bodies."""
    from sklearn.mixture import GaussianMixture

    fitted = []
    real_fit = GaussianMixture.fit

    def counted(self, x, y=None):
        fitted.append(self.init_params if self.means_init is None else "given")
        return real_fit(self, x)

    monkeypatch.setattr(GaussianMixture, "fit", counted)
    cell, up = 0.1, torch.tensor([0.0, 0.0, 1.0])
    pts, n = _long_beside_round(cell)
    track = ClusterTrack()
    first = cluster_individuals(pts, up, cell, 2, track=track)
    # the partition's start, the blobs' start, the restarts
    assert fitted == ["given"] * 2 + ["k-means++"] * clustering.MIXTURE_RESTARTS
    fitted.clear()
    assert torch.equal(cluster_individuals(pts, up, cell, 2, track=track), first)
    assert fitted == ["given"] * 3  # and the track's
    fitted.clear()
    moved = pts + torch.tensor([0.0, 6.0, 0.0])
    labels = cluster_individuals(moved, up, cell, 2, track=track)
    assert fitted == ["given"] * 3 + ["k-means++"] * clustering.MIXTURE_RESTARTS
    assert len(set(labels[:n].tolist())) == 1 and len(set(labels[n:].tolist())) == 1
    assert labels[0] != labels[-1]


def test_spanning_share_known_values():
    """Label 0 holds two points of blob 0 and one of blob 1: that one is outside its
    label's heaviest blob; labels 1 and 2 each lie in one blob. 1 of 6 points."""
    labels = np.array([0, 0, 0, 1, 1, 2])
    blobs = np.array([0, 0, 1, 1, 1, 2])
    assert _spanning_share(labels, blobs, 3) == pytest.approx(1 / 6)
    assert _spanning_share(blobs, blobs, 3) == 0.0
    assert _spanning_share(labels, None, 3) == 0.0


def test_blob_means_known_values():
    """The means of the k heaviest blobs; with more individuals than blobs, the heaviest
    part cut across its principal axis at its mean (a row of five points: 0, 1, 2 | 3, 4)."""
    row = np.array([[float(i), 0.0, 0.0] for i in range(5)])
    x = np.concatenate([row, [[0.0, 9.0, 0.0]] * 3, [[9.0, 9.0, 0.0]] * 2])
    blobs = np.repeat([0, 1, 2], [5, 3, 2])
    assert np.allclose(_blob_means(x, blobs, 2), [[2.0, 0.0, 0.0], [0.0, 9.0, 0.0]])
    four = _blob_means(x, blobs, 4)
    assert np.allclose(four[:2], [[0.0, 9.0, 0.0], [9.0, 9.0, 0.0]])
    assert np.allclose(np.sort(four[2:, 0]), [1.0, 3.5]) and np.allclose(four[2:, 1:], 0.0)


def _box(lo, hi, cell: float) -> np.ndarray:
    """Voxel centres (P, 3) filling the box from corner ``lo`` to ``hi``."""
    axes = [np.arange(a, b - 1e-9, cell) + cell / 2 for a, b in zip(lo, hi, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_two_small_bodies_apart_are_not_one_gaussian_where_a_big_one_splits_better(
        monkeypatch):
    """A big body of two lumps joined by a neck, and two small upright bodies 0.6 apart
    (three blobs). Two Gaussians fit the big body far better than one, and the two small
    ones cost one Gaussian little: by likelihood alone the partition that cuts the big
    body and joins the small ones (the k-means' here) is the better one, and it stands.
    A Gaussian that holds voxels of two blobs pays ``BLOB_PENALTY`` nats per voxel
    outside its heaviest blob: the mixture then keeps each blob one individual."""
    cell = 0.1
    big = np.concatenate([_box((0, 0, 0), (0.8, 0.6, 0.6), cell),
                          _box((0.8, 0.1, 0.1), (1.2, 0.5, 0.5), cell),
                          _box((1.2, 0, 0), (2.0, 0.6, 0.6), cell)])
    small = [_box((0, 1.5, 0), (0.2, 1.7, 1.0), cell), _box((0.8, 1.5, 0), (1.0, 1.7, 1.0), cell)]
    x = np.concatenate([big, *small])
    blobs = np.repeat([0, 1, 2], [len(big), len(small[0]), len(small[1])])
    cut = np.where(blobs == 0, (x[:, 0] > 1.0).astype(int), 2)
    assert _partition_loglik(x, cut, 3, cell**2) > _partition_loglik(x, blobs, 3, cell**2)
    assert clustering.BLOB_PENALTY > 0
    labels = _mixture_labels(x, cut, 3, cell**2, 0.02, ClusterTrack(), blobs)
    assert labels is not None and _same_partition(labels, blobs)
    monkeypatch.setattr(clustering, "BLOB_PENALTY", 0.0)
    assert _mixture_labels(x, cut, 3, cell**2, 0.02, ClusterTrack(), blobs) is None
