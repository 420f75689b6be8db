r"""Re-identification metrics of embeddings: cross-camera rank-1 and mAP.

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
"""

from __future__ import annotations

import numpy as np

__all__ = ["nearest_candidates", "pairwise_distances", "reid_metrics"]


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
