r"""The CNN re-identification baseline that texture codes are compared with.

Baseline (:class:`ReidCNN`, :func:`train_reid_baseline`)
    The texture encoder's CNN on the masked RGB crops (no NNOPCS), a BN-neck
    and an identity classifier, trained with identity cross-entropy +
    batch-hard triplet loss (margin 0.3) on P identities x K crops per batch
    (the recipe TransReID and its CNN predecessors use); its embedding is the
    BN-neck's input.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from netepu.texture.networks import TextureEncoder

__all__ = ["ReidCNN", "batch_hard_triplet_loss", "train_reid_baseline"]


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
