r"""Re-identification from embeddings: cross-camera rank-1 / mAP, figures, and a CNN baseline.

Protocol (:func:`reid_metrics`)
    Every embedding is a query once; its gallery is every embedding from
    *another camera* (same-camera entries are excluded, so a view is never
    matched to itself or to its own camera's other frames). Distance: cosine
    (``metric="cosine"``) or Euclidean. Rank-1: share of queries whose nearest
    gallery entry has the query's identity. mAP: mean over queries of the
    average precision of the ranked gallery,
    :math:`\mathrm{AP} = \frac{1}{|P|}\sum_{k \in P} \mathrm{precision@}k`
    (P: ranks of the true matches). Queries without a true match in the
    gallery are skipped (counted in ``queries_without_match``).

Figures
    :func:`tsne_kde_figure`: t-SNE of embeddings with kernel-density contours
    per identity for one subset (e.g. training cameras) and dots for another
    (held-out cameras), as NeTePu fig. 5. :func:`separation_figure`:
    histograms of same- and different-identity cross-camera distances and
    each identity's margin (nearest other identity's centroid distance over
    its own spread).

Within-class whitening (:func:`within_class_whitening`)
    A linear map fitted on labelled training codes that equalises the
    directions in which one identity's codes vary (pose, camera, shading):
    with the within-class scatter
    :math:`S_w = \frac1N \sum_i (x_i - m_{y_i})(x_i - m_{y_i})^\top`
    (:math:`m_c` the mean of identity c), its eigen-decomposition
    :math:`S_w = V \Lambda V^\top` and shrinkage
    :math:`\lambda' = \lambda \operatorname{tr}(S_w) / D`,

    .. math::
        e = (x - m) P, \qquad P = V (\Lambda + \lambda' I)^{-1/2},

    with m the mean of all training codes, so that
    :math:`P^\top (S_w + \lambda' I) P = I` (WCCN, as in speaker
    verification). Directions that identities share are scaled up, the
    within-identity spread down; no dimension is dropped, so it also serves
    identities never seen in the fit (unlike LDA, which keeps C - 1 directions).

Colour statistics (:func:`colour_statistics`)
    Re-identification reads the texture code together with six numbers of the
    encoder's masked crop: the log of the mean colour inside the mask and the
    colour's standard deviation inside the mask, per channel,

    .. math::
        c = \big(\log(\bar a + \epsilon),\ \sigma_a\big), \qquad
        \bar a = \tfrac{1}{|M|}\sum_{p \in M} a_p, \quad
        \sigma_a^2 = \tfrac{1}{|M|}\sum_{p \in M} (a_p - \bar a)^2,

    (:math:`\epsilon = 1/255`). Under Lambertian shading a colour is the albedo
    times a grey shading term, so a change of light or view moves
    :math:`\log \bar a` along :math:`(1, 1, 1)` (for shading uncorrelated with
    albedo); that is within-class variation, which the whitening below learns to
    discount, while a small difference of albedo (the look-alike pairs) is not.
    The code alone keeps the mean colour only coarsely (NeTePu's renderer needs
    it only to within its PSNR).

Shrinkage by validation (:func:`select_shrinkage`)
    The whitening's shrinkage is chosen on the training codes alone: two folds
    of training views, each fitted on one fold and scored (cross-camera rank-1,
    then mAP) on the other; the mean over both folds picks the grid value (the
    largest on ties).

Baseline (:class:`ReidCNN`, :func:`train_reid_baseline`)
    The texture encoder's CNN on the masked RGB crops (no NNOPCS), a BN-neck
    and an identity classifier, trained with identity cross-entropy +
    batch-hard triplet loss (margin 0.3) on P identities x K crops per batch
    (the recipe TransReID and its CNN predecessors use); its embedding is the
    BN-neck's input.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from netepu.texture.model import TextureEncoder

__all__ = [
    "COLOUR_STATISTICS",
    "ReidCNN",
    "batch_hard_triplet_loss",
    "colour_statistics",
    "nearest_candidates",
    "pairwise_distances",
    "reid_metrics",
    "select_shrinkage",
    "separation_figure",
    "train_reid_baseline",
    "tsne_kde_figure",
    "within_class_whitening",
]


COLOUR_STATISTICS = 6  # log mean colour (3) and colour standard deviation (3)
COLOUR_EPS = 1.0 / 255


def colour_statistics(rgb: Tensor, inside: Tensor) -> Tensor:
    """Masked colour statistics of crops (module docstring).

    Args:
        rgb: (B, S, S, 3) colours in [0, 1]; inside: (B, S, S) bool, the pixels that count.

    Returns:
        (B, 6): log(mean colour + 1/255) and the colour's standard deviation, per
        channel, over the pixels inside; log(1/255) and 0 for an empty mask.
    """
    w = inside.to(rgb.dtype)[..., None]
    n = w.sum((1, 2)).clamp(min=1)
    mean = (rgb * w).sum((1, 2)) / n
    var = ((rgb - mean[:, None, None]) ** 2 * w).sum((1, 2)) / n
    return torch.cat([torch.log(mean + COLOUR_EPS), var.sqrt()], -1)


def select_shrinkage(
    codes: np.ndarray,
    labels: np.ndarray,
    cameras: np.ndarray,
    groups: np.ndarray,
    grid: tuple[float, ...] = (0.1, 0.01, 0.001, 0.0001),
) -> tuple[float, dict[float, float]]:
    """The whitening shrinkage that re-identifies best across two folds of training codes.

    Args:
        codes: (N, D); labels: (N,) identities; cameras: (N,) camera ids.
        groups: (N,) ordered group ids (e.g. training views, so that one view never sits in
            both folds); fold 1 holds the groups >= their median, fold 0 the others.
        grid: shrinkage values to try.

    Returns:
        ``(best, scores)``: ``scores[s]`` is the mean over both folds of the other fold's
        cross-camera rank-1 plus 1e-3 x its mAP; ties go to the larger shrinkage.

    Raises:
        ValueError: an empty grid, a fold with fewer than two identities, or a fold
            without a query that has a match in another camera.
    """
    if not grid:
        raise ValueError("select_shrinkage: the grid is empty")
    codes, labels = np.asarray(codes, np.float64), np.asarray(labels)
    cameras, groups = np.asarray(cameras), np.asarray(groups)
    folds = (groups >= np.median(groups)).astype(np.int64)
    scores = {}
    for shrinkage in sorted(grid, reverse=True):
        total = 0.0
        for fit in (0, 1):
            a, b = folds == fit, folds != fit
            if len(np.unique(labels[a])) < 2:
                raise ValueError(f"select_shrinkage: fold {fit} holds fewer than 2 identities")
            m, p = within_class_whitening(codes[a], labels[a], shrinkage)
            r = reid_metrics((codes[b] - m) @ p, labels[b], cameras[b])
            if not r["queries"]:
                raise ValueError(
                    f"select_shrinkage: no code of fold {1 - fit} has a match in another camera"
                )
            total += r["rank1"] + 1e-3 * r["map"]
        scores[float(shrinkage)] = total / 2
    best = max(scores, key=lambda k: (scores[k], k))
    return best, scores


def within_class_whitening(
    codes: np.ndarray, labels: np.ndarray, shrinkage: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Fit the within-class whitening (module docstring) on labelled codes.

    Args:
        codes: (N, D) training codes; labels: (N,) their identities (>= 2 distinct).
        shrinkage: lambda >= 0, relative to the mean eigenvalue of S_w.

    Returns:
        ``(m (D,), P (D, D))`` float64: the embedding of x is ``(x - m) @ P``.

    Raises:
        ValueError: fewer than two identities, a negative shrinkage, non-finite codes,
            or a singular scatter with no shrinkage.
    """
    x = np.asarray(codes, np.float64)
    y = np.asarray(labels)
    if x.ndim != 2 or len(x) != len(y):
        raise ValueError(f"whitening: codes (N, D) and labels (N,), got {x.shape}, {y.shape}")
    if shrinkage < 0 or not np.isfinite(x).all():
        raise ValueError("whitening: shrinkage must be >= 0 and the codes finite")
    classes, index = np.unique(y, return_inverse=True)
    if len(classes) < 2:
        raise ValueError(f"whitening: needs >= 2 identities, got {len(classes)}")
    means = np.stack([x[index == c].mean(0) for c in range(len(classes))])
    centred = x - means[index]
    scatter = centred.T @ centred / len(x)
    ev, vec = np.linalg.eigh(scatter)
    ev = ev + shrinkage * max(float(np.trace(scatter)), 0.0) / x.shape[1]
    if ev.min() <= 1e-12 * max(float(ev.max()), 1e-300):
        raise ValueError(
            "whitening: the within-class scatter is singular (too few codes per dimension); "
            "give a shrinkage > 0"
        )
    return x.mean(0), vec / np.sqrt(ev)


def pairwise_distances(a: np.ndarray, b: np.ndarray, metric: str = "cosine") -> np.ndarray:
    """Distances (n, m) between rows of a (n, d) and b (m, d).

    ``metric``: ``cosine`` (1 - cosine similarity) or ``euclidean``.
    """
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if metric == "cosine":
        a = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
        b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
        return 1.0 - a @ b.T
    if metric == "euclidean":
        d = (a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T
        return np.sqrt(np.maximum(d, 0))
    raise ValueError(f"metric must be 'cosine' or 'euclidean', got {metric!r}")


def nearest_candidates(
    embeddings: np.ndarray, candidates: np.ndarray, metric: str = "cosine", chunk: int = 1024
) -> np.ndarray:
    """For each row, the index of its nearest row among its candidates.

    Args:
        embeddings: (n, d).
        candidates: (n, n) bool, row i may retrieve row j (e.g. another camera of the
            same frame).

    Returns:
        (n,) int64 indices; -1 for rows without a candidate.
    """
    candidates = np.asarray(candidates, bool)
    n = len(embeddings)
    if candidates.shape != (n, n):
        raise ValueError(f"candidates must be ({n}, {n}), got {candidates.shape}")
    out = np.full(n, -1, np.int64)
    for s in range(0, n, chunk):
        q = slice(s, min(n, s + chunk))
        d = np.where(candidates[q], pairwise_distances(embeddings[q], embeddings, metric), np.inf)
        best = d.argmin(1)
        out[q] = np.where(candidates[q].any(1), best, -1)
    return out


def reid_metrics(
    embeddings: np.ndarray,
    ids: np.ndarray,
    cameras: np.ndarray,
    metric: str = "cosine",
    chunk: int = 1024,
) -> dict[str, float]:
    """Cross-camera rank-1 and mAP (see the module docstring).

    Args:
        embeddings: (n, d).
        ids: (n,) identities; cameras: (n,) camera ids.

    Returns:
        ``rank1``, ``map`` in [0, 1], ``queries``, ``queries_without_match``.
    """
    ids, cameras = np.asarray(ids), np.asarray(cameras)
    n = len(ids)
    hits, aps, skipped = [], [], 0
    for s in range(0, n, chunk):
        q = np.arange(s, min(n, s + chunk))
        d = pairwise_distances(embeddings[q], embeddings, metric)
        d[cameras[q][:, None] == cameras[None]] = np.inf
        order = np.argsort(d, axis=1, kind="stable")
        for row, qi in enumerate(q):
            o = order[row]
            o = o[np.isfinite(d[row, o])]
            match = ids[o] == ids[qi]
            if not match.any():
                skipped += 1
                continue
            hits.append(bool(match[0]))
            ranks = np.nonzero(match)[0]
            aps.append(float(np.mean(np.arange(1, len(ranks) + 1) / (ranks + 1))))
    return {
        "rank1": float(np.mean(hits)) if hits else float("nan"),
        "map": float(np.mean(aps)) if aps else float("nan"),
        "queries": float(len(hits)),
        "queries_without_match": float(skipped),
    }


# ----------------------------------------------------------------------------- figures
def tsne_kde_figure(
    embeddings: np.ndarray,
    ids: np.ndarray,
    dots: np.ndarray,
    path,
    title: str,
    names: dict[int, str] | None = None,
    seed: int = 0,
    metric: str = "cosine",
) -> None:
    """t-SNE with KDE contours per identity (``~dots``) and dots (``dots``), saved to ``path``.

    Args:
        embeddings: (n, d); ids: (n,); dots: (n,) bool, entries drawn as dots.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import gaussian_kde
    from sklearn.manifold import TSNE

    x = embeddings.astype(np.float64)
    if metric == "cosine":
        x = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    y = TSNE(
        2, perplexity=min(30, max(5, len(x) // 20)), init="pca", random_state=seed
    ).fit_transform(x)
    fig, ax = plt.subplots(figsize=(7, 6))
    cmap = plt.get_cmap("tab20")
    lo, hi = y.min(0) - 5, y.max(0) + 5
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 120), np.linspace(lo[1], hi[1], 120))
    for k, i in enumerate(np.unique(ids)):
        c = cmap(k % 20)
        sel = (ids == i) & ~dots
        if sel.sum() >= 3:
            kde = gaussian_kde(y[sel].T)
            z = kde(np.stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
            # levels relative to the peak: matplotlib's automatic lowest level sits at
            # ~0 density, where contours of numerical noise run across the whole plot
            ax.contour(
                gx,
                gy,
                z,
                levels=z.max() * np.array([0.1, 0.3, 0.5, 0.7]),
                colors=[c],
                linewidths=0.8,
            )
        d = (ids == i) & dots
        ax.scatter(y[d, 0], y[d, 1], s=6, color=c, label=(names or {}).get(int(i), str(int(i))))
    ax.set_title("\n".join(textwrap.wrap(title, 80)), fontsize=10)  # long titles fit
    ax.set_xticks([])
    ax.set_yticks([])
    ax.legend(fontsize=6, ncol=2, loc="best", markerscale=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _margins(embeddings: np.ndarray, ids: np.ndarray, metric: str) -> tuple[np.ndarray, list]:
    """Per identity: nearest other identity's centroid distance / own mean distance to centroid."""
    x = embeddings.astype(np.float64)
    if metric == "cosine":
        x = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    u = np.unique(ids)
    cent = np.stack([x[ids == i].mean(0) for i in u])
    spread = np.array(
        [pairwise_distances(x[ids == i], cent[k : k + 1], metric).mean() for k, i in enumerate(u)]
    )
    dc = pairwise_distances(cent, cent, metric)
    np.fill_diagonal(dc, np.inf)
    return dc.min(1) / np.maximum(spread, 1e-12), [int(u[j]) for j in dc.argmin(1)]


def separation_figure(
    results: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    path,
    metric: str = "cosine",
    max_pairs: int = 200000,
    seed: int = 0,
) -> dict[str, dict[str, float]]:
    """Cluster separation of several embeddings, saved to ``path``.

    Args:
        results: name -> (embeddings (n, d), ids (n,), cameras (n,)).

    Returns:
        name -> ``{"margin_min": ..., "margin_median": ..., "overlap": ...}`` where
        ``overlap`` is the share of different-identity cross-camera pairs closer
        than the median same-identity cross-camera pair.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(seed)
    fig, axes = plt.subplots(2, len(results), figsize=(5 * len(results), 7), squeeze=False)
    summary = {}
    for col, (name, (emb, ids, cams)) in enumerate(results.items()):
        n = len(ids)
        a, b = rng.integers(0, n, max_pairs), rng.integers(0, n, max_pairs)
        keep = cams[a] != cams[b]
        a, b = a[keep], b[keep]
        x = emb.astype(np.float64)
        if metric == "cosine":
            x = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
            d = 1 - (x[a] * x[b]).sum(1)
        else:
            d = np.linalg.norm(x[a] - x[b], axis=1)
        same = ids[a] == ids[b]
        ax = axes[0, col]
        bins = np.linspace(0, np.percentile(d, 99.5), 80)
        ax.hist(d[same], bins, alpha=0.6, density=True, label="same identity")
        ax.hist(d[~same], bins, alpha=0.6, density=True, label="different identity")
        ax.set_title(f"{name}: cross-camera {metric} distances", fontsize=9)
        ax.legend(fontsize=7)
        margin, nearest = _margins(emb, ids, metric)
        ax = axes[1, col]
        u = np.unique(ids)
        ax.bar(np.arange(len(u)), margin, color="tab:blue")
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_xticks(
            np.arange(len(u)),
            [f"{int(i)}\n({j})" for i, j in zip(u, nearest, strict=True)],
            fontsize=6,
        )
        ax.set_title(
            "margin per identity: nearest other centroid / own spread (nearest in brackets)",
            fontsize=8,
        )
        summary[name] = {
            "margin_min": float(margin.min()),
            "margin_median": float(np.median(margin)),
            "overlap": float((d[~same] < np.median(d[same])).mean()),
        }
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return summary


# ----------------------------------------------------------------------------- baseline
class ReidCNN(nn.Module):
    """Baseline re-id network: the texture encoder's CNN on masked RGB crops + BN-neck + classifier.

    Args:
        n_ids: training identities.
        widths, blocks_per_stage: CNN sizes (as the texture encoder).
        dims: embedding size.

    Shape:
        (B, 4, S, S) (masked RGB + mask) -> embedding (B, dims), logits (B, n_ids).
    """

    def __init__(
        self, n_ids: int, widths: list[int], blocks_per_stage: int = 2, dims: int = 128
    ) -> None:
        super().__init__()
        self.backbone = TextureEncoder(4, dims, widths, blocks_per_stage)
        self.proj = nn.Linear(widths[-1], dims)
        self.neck = nn.BatchNorm1d(dims)
        self.classifier = nn.Linear(dims, n_ids, bias=False)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        emb = self.proj(self.backbone.features(x))
        return emb, self.classifier(self.neck(emb))


def batch_hard_triplet_loss(emb: Tensor, ids: Tensor, margin: float = 0.3) -> Tensor:
    """Batch-hard triplet loss (Hermans et al. 2017) on Euclidean distances; scalar."""
    d = torch.cdist(emb, emb)
    same = ids[:, None] == ids[None]
    pos = torch.where(same, d, torch.zeros_like(d)).amax(1)
    neg = torch.where(same, torch.full_like(d, float("inf")), d).amin(1)
    return F.relu(pos - neg + margin).mean()


def train_reid_baseline(
    model: ReidCNN,
    sample: Callable[[np.ndarray], Tensor],
    ids: np.ndarray,
    steps: int | None = None,
    minutes: float | None = None,
    p_ids: int = 8,
    k_per_id: int = 4,
    lr: float = 1e-3,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
) -> dict[str, float]:
    """Train the baseline with identity CE + batch-hard triplet loss on P x K batches.

    Args:
        sample: indices (n,) -> encoder input (n, 4, S, S).
        ids: (N,) identity of every training sample (0 .. n_ids - 1).
        steps / minutes: budget (whichever ends first; at least one).

    Returns:
        ``steps``, ``minutes``, last ``loss``.
    """
    import time

    if steps is None and minutes is None:
        raise ValueError("train_reid_baseline: give steps or minutes")
    rng = np.random.default_rng(seed)
    by_id = {int(i): np.nonzero(ids == i)[0] for i in np.unique(ids)}
    keys = np.array(sorted(by_id))
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=5e-4)
    model.train()
    t0, step, loss = time.perf_counter(), 0, torch.tensor(float("nan"))
    while True:
        if steps is not None and step >= steps:
            break
        if minutes is not None and time.perf_counter() - t0 >= 60 * minutes:
            break
        chosen = rng.choice(keys, min(p_ids, len(keys)), replace=False)
        idx = np.concatenate([rng.choice(by_id[int(i)], k_per_id) for i in chosen])
        y = torch.from_numpy(ids[idx]).long()
        emb, logits = model(sample(idx))
        loss = F.cross_entropy(logits, y) + batch_hard_triplet_loss(emb, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        if log and step % 100 == 0:
            log(f"baseline step {step}: loss {loss.item():.4f}")
    model.eval()
    return {
        "steps": float(step),
        "minutes": (time.perf_counter() - t0) / 60,
        "loss": float(loss.detach()),
    }
