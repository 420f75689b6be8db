r"""Depth compositing of subject layers over a background (NSD eq. 6-7, supplement D).

erf-transmittance compositor
----------------------------
Each subject :math:`i` is a translucent layer at depth :math:`z_i` (smaller is
nearer) with a Gaussian density along the ray, scaled per pixel by its mask
:math:`S_i \in [0, 1]`. By Beer-Lambert with :math:`\sigma = 1/\sqrt 2`, the
transmittance from the camera to depth :math:`z` is

.. math::
    T(z) = \exp\Big(-\sum_i S_i\,\big(\operatorname{erf}(z - z_i) + 1\big)\Big),
    \qquad T(\infty) = \exp\Big(-2 \sum_i S_i\Big).

(The paper prints :math:`\operatorname{erf}(z_i - z)`; with that sign a layer
would block light in *front* of itself. We use the physical axis: the
transmittance to :math:`z` drops once :math:`z` passes :math:`z_i`.)

The visibility of subject :math:`j` is :math:`T(z_j) S_j`; a normalisation
:math:`Z` makes subjects and background share the pixel exactly:

.. math::
    w_j = T(z_j)\,S_j\,Z, \quad Z = \frac{1 - T(\infty)}{\sum_k T(z_k) S_k},
    \qquad \sum_j w_j + T(\infty) = 1,

    \hat I = \sum_j w_j I_j + T(\infty)\,B, \qquad
    \hat D = \frac{\sum_j w_j z_j}{\sum_j w_j}.

The weights :math:`w_j` are the instance masks; :math:`\hat D` is the depth map
of the subjects (where any is visible).

Worked cases: one opaque subject alone gets :math:`w = 1 - e^{-2}` and leaks
:math:`e^{-2}` (13.5 %) background; two opaque subjects at depths 0 and 3 get
0.865 and 0.117 with :math:`T(\infty) = e^{-4}`; swapping the depths swaps them.

Stable evaluation: with the subject mass :math:`m = \sum_i S_i` per pixel,
:math:`Z` is evaluated as

.. math::
    Z = \frac{\phi(m)}{r}, \qquad
    \phi(m) = \frac{1 - e^{-2m}}{m}, \qquad
    r = \frac{\sum_k T(z_k) S_k}{m} \in [e^{-2N}, 1],

the ratio of two quantities that both vanish like :math:`m` as the masks go to
0 rewritten as a ratio of two bounded ones (:math:`r` is the mask-weighted
mean of the transmittances). :math:`\phi` is a power series below
``SERIES_BELOW`` (its limit :math:`\phi(0) = 2`; the closed form loses its
gradient to cancellation there) and :math:`r = 1` where :math:`m` is below the
dtype's machine epsilon (its limit: every transmittance is 1 within
:math:`2m`). So the weights and their gradients keep their limits where every
mask is exactly 0 (background weight 1, :math:`\partial w_j/\partial S_j = 2`:
a transparent subject still learns to appear) instead of a 0/0 that a clamp
would have to turn into a zero gradient. :math:`\operatorname{erf} \in [-1, 1]`
bounds every exponent to :math:`[-2N, 0]`, so no exponential over- or
underflows whatever the depths (1e4 apart or equal), and :math:`1/r \le
e^{2N}`. The background weight is returned as :math:`1 - \sum_j w_j`, so the
weights sum to exactly 1 by construction, and equals :math:`T(\infty)`. The
depth map divides by the subject coverage clamped at ``DEPTH_FLOOR`` (1e-6):
where subjects cover less of a pixel it fades to 0 (no subject), keeping its
gradient bounded by :math:`|z| / \text{DEPTH\_FLOOR}`. The cost is
:math:`O(N^2 HW)`: an (N, N) matrix of erf terms applied to the masks.

Additive compositor (NSD eq. 6, the "no depth reasoning" ablation)
--------------------------------------------------------------------
:math:`w_i = S_i / \max(1, \sum_k S_k)`, background weight :math:`1 - \sum_i w_i`:
overlapping layers blend instead of occluding.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

__all__ = [
    "Composite",
    "additive_composite",
    "blend",
    "erf_transmittance_composite",
    "masks_overlap",
    "separate_composite",
]

SERIES_BELOW = 1e-2  # masses m below this use the power series of phi(m) (module docstring)
DEPTH_FLOOR = 1e-6  # subject coverage below which the depth map fades to 0


class Composite(NamedTuple):
    """Compositing result.

    Attributes:
        weights: per-subject visibility / instance masks, (B, N, H, W).
        background_weight: (B, H, W); ``weights.sum(1) + background_weight == 1``.
        depth: expected subject depth where subjects are visible, (B, H, W).
    """

    weights: Tensor
    background_weight: Tensor
    depth: Tensor


def _check(masks: Tensor, depths: Tensor) -> None:
    if masks.dim() != 4:
        raise ValueError(f"masks must be (B, N, H, W), got {tuple(masks.shape)}")
    if depths.shape != masks.shape[:2]:
        raise ValueError(
            f"depths must be (B, N) = {tuple(masks.shape[:2])}, got {tuple(depths.shape)}"
        )


def _depth_map(weights: Tensor, depths: Tensor) -> Tensor:
    total = weights.sum(1)
    return (weights * depths[..., None, None]).sum(1) / total.clamp_min(DEPTH_FLOOR)


def _coverage_per_mass(mass: Tensor) -> Tensor:
    """:math:`\\phi(m) = (1 - e^{-2m}) / m` for masses m >= 0, with phi(0) = 2.

    Below ``SERIES_BELOW`` the Taylor series (truncation < 1e-16 relative), above
    it the closed form, whose autograd gradient is accurate there (relative error
    ~ machine epsilon / m).
    """
    small = mass < SERIES_BELOW
    safe = torch.where(small, torch.ones_like(mass), mass)  # no 0/0 in the unused branch
    closed = -torch.expm1(-2 * safe) / safe
    x = 2 * mass
    # (1 - e^-x) / x = sum_k (-x)^k / (k + 1)!, Horner form up to x^6
    series = 1 - x / 2 * (1 - x / 3 * (1 - x / 4 * (1 - x / 5 * (1 - x / 6 * (1 - x / 7)))))
    return torch.where(small, 2 * series, closed)


def erf_transmittance_composite(masks: Tensor, depths: Tensor) -> Composite:
    """Visibility weights of depth-ordered translucent layers (see the module docstring).

    Args:
        masks: subject masks :math:`S`, (B, N, H, W), values in [0, 1].
        depths: one depth per subject :math:`z`, (B, N); smaller is nearer.

    Returns:
        :class:`Composite` with weights (B, N, H, W), background weight (B, H, W)
        and depth map (B, H, W).

    Example:
        >>> c = erf_transmittance_composite(torch.ones(1, 2, 1, 1), torch.tensor([[0.0, 3.0]]))
        >>> [round(v, 3) for v in c.weights.flatten().tolist()]
        [0.865, 0.117]
    """
    _check(masks, depths)
    # E[b, j, i] = erf(z_j - z_i) + 1: how much of layer i lies in front of z_j
    E = torch.erf(depths.unsqueeze(-1) - depths.unsqueeze(-2)) + 1
    optical_depth = torch.einsum("bji,bihw->bjhw", E, masks)  # -log T(z_j), in [0, 2N]
    visible = torch.exp(-optical_depth) * masks  # T(z_j) S_j
    mass = masks.sum(1)  # m
    seen = mass > torch.finfo(masks.dtype).eps
    mean_transmittance = torch.where(  # r, 1 where m ~ 0 (its limit)
        seen, visible.sum(1) / torch.where(seen, mass, torch.ones_like(mass)), 1.0
    )
    weights = visible * (_coverage_per_mass(mass) / mean_transmittance).unsqueeze(1)
    background = 1 - weights.sum(1)
    return Composite(weights, background, _depth_map(weights, depths))


def masks_overlap(masks: Tensor, eps: float = 1e-6) -> Tensor:
    """Per sample, whether any pixel holds two subjects with mask > ``eps``: (B,) bool."""
    return ((masks > eps).sum(1) > 1).flatten(1).any(1)


def separate_composite(masks: Tensor, depths: Tensor) -> Composite:
    """The erf compositor's exact result when no two masks overlap (occlusion skipped).

    With a single subject at a pixel, :math:`T(z_j) = e^{-S_j}`, the normalisation
    gives :math:`w_j = 1 - e^{-2 S_j}` and the background keeps :math:`e^{-2 S_j}`;
    no pair of subjects interacts, so the (N, N) erf matrix is not needed.

    Args:
        masks: (B, N, H, W) with at most one non-zero mask per pixel.
        depths: (B, N) (only for the depth map).
    """
    _check(masks, depths)
    weights = -torch.expm1(-2 * masks)
    return Composite(weights, 1 - weights.sum(1), _depth_map(weights, depths))


def additive_composite(masks: Tensor, depths: Tensor) -> Composite:
    """NSD eq. 6: layers add up (clamped to a partition of unity); depth is ignored.

    Args:
        masks: (B, N, H, W) in [0, 1].
        depths: (B, N), only used for the returned depth map.
    """
    _check(masks, depths)
    weights = masks / masks.sum(1, keepdim=True).clamp_min(1.0)
    return Composite(weights, 1 - weights.sum(1), _depth_map(weights, depths))


def blend(composite: Composite, layers: Tensor, background: Tensor) -> Tensor:
    """The composited image :math:`\\sum_j w_j I_j + w_{bg} B`.

    Args:
        composite: weights from a compositor.
        layers: subject images, (B, N, C, H, W).
        background: (B, C, H, W).

    Returns:
        (B, C, H, W).
    """
    fg = (composite.weights.unsqueeze(2) * layers).sum(1)
    return fg + composite.background_weight.unsqueeze(1) * background
