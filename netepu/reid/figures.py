r"""Re-identification figures: t-SNE with density contours, distance histograms.

Figures
    :func:`tsne_kde_figure`: t-SNE of embeddings with kernel-density contours
    per identity for one subset (e.g. training cameras) and dots for another
    (held-out cameras), as NeTePu fig. 5. :func:`separation_figure`:
    histograms of same- and different-identity cross-camera distances and
    each identity's margin (nearest other identity's centroid distance over
    its own spread).
"""

from __future__ import annotations

import textwrap

import numpy as np
from scipy.stats import gaussian_kde

from nsd.evaluation.reid import pairwise_distances

__all__ = ["separation_figure", "tsne_kde_figure"]


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
    # lazy: matplotlib (0.3 s to import) only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # lazy: scikit-learn (0.7 s to import) only for the t-SNE figure
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
    # lazy: matplotlib (0.3 s to import) only when a figure is drawn
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
