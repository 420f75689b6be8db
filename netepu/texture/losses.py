r"""The texture stage's loss terms: colour, KLD and the optional code contrast.

Loss (:func:`texture_loss`): :math:`\lambda_{col}` MSE of colour on in-mask
points + :math:`\lambda_{KLD}` KLD (eq. 8; defaults 5 and 1e-8), with
:math:`\mathrm{KLD} = -\tfrac12 \sum_d (1 + \log\sigma_d^2 - \mu_d^2 - \sigma_d^2)`
averaged over the batch.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["code_contrast_loss", "kld", "reparameterise", "texture_loss"]


# ----------------------------------------------------------------------------- losses
def reparameterise(mu: Tensor, logvar: Tensor, noise: Tensor | None = None) -> Tensor:
    """z = mu + exp(logvar / 2) * eps, eps ~ N(0, I) (or ``noise``); shapes (B, d_z)."""
    eps = torch.randn_like(mu) if noise is None else noise
    return mu + torch.exp(0.5 * logvar) * eps


def kld(mu: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)) summed over dimensions, mean over the batch; scalar."""
    return (-0.5 * (1 + logvar - mu.square() - logvar.exp()).sum(-1)).mean()


def code_contrast_loss(mu: Tensor, partner: Tensor, same: Tensor, temperature: float) -> Tensor:
    r"""Supervised contrastive loss between texture codes of two views of the same batch.

    With unit codes :math:`u_i = \mu_i / \lVert\mu_i\rVert` of the batch and
    :math:`u'_j` of the partner views (each another pose and camera of the
    texture of row :math:`j`), and :math:`P(i) = \{j : \text{same}_{ij}\}`,

    .. math::
        L = -\frac{1}{B}\sum_i \log
            \frac{\sum_{j \in P(i)} e^{u_i \cdot u'_j / \tau}}
                  {\sum_{j} e^{u_i \cdot u'_j / \tau}} ,

    computed with log-sum-exp. It pulls the codes of one texture seen in
    different views together and pushes those of other textures apart: what
    re-identification needs, and what a reconstruction loss alone does not ask.

    Args:
        mu: codes (B, D); partner: codes (B, D) of the partner views.
        same: (B, B) bool, row i and partner j show the same texture (the
            diagonal is True).
        temperature: :math:`\tau` > 0.

    Returns:
        Scalar.
    """
    if temperature <= 0:
        raise ValueError(f"code_contrast_loss: temperature must be > 0, got {temperature}")
    u = F.normalize(mu, dim=-1, eps=1e-12)
    v = F.normalize(partner, dim=-1, eps=1e-12)
    logits = u @ v.T / temperature
    positive = logits.masked_fill(~same, float("-inf"))
    return (torch.logsumexp(logits, -1) - torch.logsumexp(positive, -1)).mean()


def texture_loss(
    colour: Tensor,
    target: Tensor,
    mu: Tensor,
    logvar: Tensor,
    w_colour: float = 5.0,
    w_kld: float = 1e-8,
) -> dict[str, Tensor]:
    """Eq. 8: ``w_colour`` MSE(colour (B, P, 3), target) + ``w_kld`` KLD; returns the terms."""
    col = F.mse_loss(colour, target)
    k = kld(mu, logvar)
    return {"colour": col, "kld": k, "loss": w_colour * col + w_kld * k}
