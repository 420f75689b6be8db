"""Looking at embeddings: a bounded random sample, the TensorBoard projector and a t-SNE plot.

Both views need the vectors in memory, so :class:`Reservoir` keeps a uniform
random sample of at most ``capacity`` rows of a stream of any length (Vitter's
algorithm R, seeded), with a small thumbnail of each subject's crop.
:func:`write_projector` writes the sample for TensorBoard's projector
(``add_embedding`` with the thumbnails as label images and subject id, camera
and frame as metadata); :func:`plot_tsne` embeds it in 2-D with scikit-learn's
t-SNE and plots it coloured by subject id.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

__all__ = ["Reservoir", "plot_tsne", "write_projector"]


class Reservoir:
    """A uniform random sample of at most ``capacity`` rows (algorithm R).

    Args:
        capacity: largest sample.
        seed: random seed (the same stream gives the same sample).

    Attributes:
        vectors: list of (D,) arrays; ``thumbs`` list of uint8 (h, w, 3);
        ``meta`` list of (subject_id, camera, frame).
    """

    def __init__(self, capacity: int, seed: int = 0) -> None:
        self.capacity = capacity
        self.rng = np.random.default_rng(seed)
        self.seen = 0
        self.vectors: list[np.ndarray] = []
        self.thumbs: list[np.ndarray] = []
        self.meta: list[tuple[int, str, int]] = []

    def offer(self, vector: np.ndarray, thumb: np.ndarray, meta: tuple[int, str, int]) -> None:
        """Consider one row for the sample."""
        k = self.seen
        self.seen += 1
        if k < self.capacity:
            self.vectors.append(vector)
            self.thumbs.append(thumb)
            self.meta.append(meta)
            return
        j = int(self.rng.integers(0, k + 1))
        if j < self.capacity:
            self.vectors[j], self.thumbs[j], self.meta[j] = vector, thumb, meta

    def __len__(self) -> int:
        return len(self.vectors)


def write_projector(sample: Reservoir, log_dir: str | os.PathLike, tag: str = "subjects") -> None:
    """TensorBoard projector files of the sample under ``log_dir``."""

    if len(sample) == 0:
        return
    mat = torch.as_tensor(np.stack(sample.vectors), dtype=torch.float32)
    thumbs = torch.as_tensor(np.stack(sample.thumbs)).permute(0, 3, 1, 2).float() / 255.0
    meta = [[str(s), c, str(f)] for s, c, f in sample.meta]
    with SummaryWriter(str(log_dir)) as w:
        w.add_embedding(
            mat,
            metadata=meta,
            label_img=thumbs,
            tag=tag,
            metadata_header=["subject_id", "camera", "frame"],
        )


def plot_tsne(
    sample: Reservoir, path: str | os.PathLike, perplexity: float = 30.0, seed: int = 0
) -> bool:
    """t-SNE of the sample coloured by subject id, saved as an image; False if too few rows.

    The perplexity is lowered to ``(n - 1) / 3`` for small samples (scikit-learn
    requires it below n).
    """
    n = len(sample)
    if n < 5:
        return False
    # lazy: matplotlib (0.3 s to import) only when a figure is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # lazy: scikit-learn (0.7 s to import) only for the t-SNE figure
    from sklearn.manifold import TSNE

    x = np.stack(sample.vectors).astype(np.float32)
    ids = np.array([m[0] for m in sample.meta])
    xy = TSNE(
        n_components=2, perplexity=min(perplexity, (n - 1) / 3), init="pca", random_state=seed
    ).fit_transform(x)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=100)
    uniq = np.unique(ids)
    cmap = plt.get_cmap("tab20")
    for k, s in enumerate(uniq):
        sel = ids == s
        ax.scatter(xy[sel, 0], xy[sel, 1], s=6, color=cmap(k % 20), label=f"subject {s}")
    if len(uniq) <= 20:
        ax.legend(markerscale=3, fontsize=7, loc="best")
    ax.set_title(f"appearance vectors, t-SNE ({n} of {sample.seen} rows)")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return True
