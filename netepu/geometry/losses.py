r"""Training losses of the geometry pipeline (NePu's composite loss with NeTePu's NNOPCS term).

With ``S`` silhouette points, ``P`` in-mask points per view and ``B`` views:

.. math::
    \mathcal L = \lambda_{sil}\,\mathrm{BCE}(\hat s, s)
    + \lambda_{kps}\,\tfrac{1}{BK}\textstyle\sum \lVert \hat x - x \rVert_2
    + \lambda_{depth}\,\tfrac{1}{B}\textstyle\sum_b \lVert \hat d_b - d_b \rVert_2
    + \lambda_{NNOPCS}\,\mathrm{MSE}(\hat P, P)
    + \lambda_{z}\,\tfrac{1}{B}\textstyle\sum_b \lVert z_b \rVert_2

* BCE on silhouette logits, mean over points (NePu: 3x, 1500 points).
* Keypoint term: mean Euclidean distance of decoded to input keypoints in the
  encoder's normalised units (NePu: 2x).
* Depth: the 2-norm over a view's in-mask points of the normalised-depth error,
  averaged over views (NeTePu sec. 5.1 prefers it to NePu's MSE).
* NNOPCS: MSE over in-mask points and the 3 channels (NeTePu eq. 6, weight 1).
* Latent: :math:`\lVert z \rVert / 16` (weight 1/16).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch.nn.functional as F
from torch import Tensor

from nsd.core.config import ConfigSection

__all__ = [
    "GeometryLossWeights",
    "depth_loss",
    "geometry_loss",
    "keypoint_loss",
    "latent_loss",
    "nnopcs_loss",
    "occlusion_aware_silhouette_loss",
    "silhouette_loss",
]


@dataclass
class GeometryLossWeights(ConfigSection):
    """Loss weights (NePu / NeTePu defaults; every field is a config value)."""

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml, section `netepu.loss`
    KEY: ClassVar[str] = "netepu.loss"

    silhouette: float
    keypoints: float
    depth: float
    nnopcs: float
    latent: float


def silhouette_loss(logit: Tensor, label: Tensor) -> Tensor:
    """Mean binary cross-entropy of logits (B, S) against labels (B, S) in {0, 1}."""
    return F.binary_cross_entropy_with_logits(logit, label)


def occlusion_aware_silhouette_loss(logit: Tensor, label: Tensor, ignored: Tensor) -> Tensor:
    r"""BCE per row of points where the ``ignored`` points do not count (inverse rendering).

    :math:`\sum_p w_p \mathrm{BCE}_p / \sum_p w_p` with :math:`w_p = 1 - \text{ignored}_p`
    (a row whose points are all ignored: 0).

    Args:
        logit, label: (N, P) silhouette logits and {0, 1} labels.
        ignored: (N, P) bool, points covered by another subject where this one is not seen.

    Returns:
        (N,) loss per row.
    """
    weight = (~ignored).to(logit.dtype)
    bce = F.binary_cross_entropy_with_logits(logit, label, reduction="none")
    return (bce * weight).sum(-1) / weight.sum(-1).clamp(min=1)


def keypoint_loss(decoded: Tensor, target: Tensor) -> Tensor:
    """Mean Euclidean distance of keypoints (B, K, 3) (both in the same units)."""
    return (decoded - target).norm(dim=-1).mean()


def depth_loss(pred: Tensor, target: Tensor) -> Tensor:
    """2-norm over points of the depth error per view (B, P), averaged over views."""
    return (pred - target).norm(dim=-1).mean()


def nnopcs_loss(pred: Tensor, target: Tensor) -> Tensor:
    """Mean squared error of NNOPCS values (B, P, 3)."""
    return F.mse_loss(pred, target)


def latent_loss(z: Tensor) -> Tensor:
    """Mean 2-norm of the global codes (B, d_z)."""
    return z.norm(dim=-1).mean()


def geometry_loss(terms: dict[str, Tensor], weights: GeometryLossWeights) -> dict[str, Tensor]:
    """Weighted sum of the unweighted terms ``silhouette, keypoints, depth, nnopcs, latent``.

    Returns:
        The input terms plus ``"loss"``, the weighted sum.
    """
    total = sum(getattr(weights, k) * v for k, v in terms.items())
    return {**terms, "loss": total}
