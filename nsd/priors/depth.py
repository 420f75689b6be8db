r"""Depth-consistency prior: detector depths ordered as the triangulated ones.

The triangulated depths come from :mod:`nsd.cues.triangulation`.

The *depth prior* asks the detector's depths to order windows as their
triangulated depths do, up to an offset per frame (the erf compositor only
uses depth differences):

.. math::
    L_{depth} = \frac{1}{|V|}\sum_{j \in V}
        \Big((z_j - \bar z) - \frac{D_j - \bar D}{\delta}\Big)^2,

with :math:`\delta` the metric depth of one compositor unit (``unit``,
0.3 m: subjects 0.5 m apart are then 1.7 units apart, erf(1.7) = 0.98) and
means over the valid windows of a frame. Targets are detached; associations
are the argmax of the soft association. It uses no labels.
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["depth_prior"]


def depth_prior(depths: Tensor, target: Tensor, valid: Tensor, unit: float = 0.3) -> Tensor:
    """Relative depth consistency (see the module docstring).

    Args:
        depths: detector depths z (B, N).
        target: triangulated camera-space depths D (B, N), metres.
        valid: (B, N) bool.
        unit: metres per compositor depth unit.
    """
    v = valid.to(depths.dtype)
    n = v.sum(1, keepdim=True)
    use = (n >= 2).to(depths.dtype) * v  # a frame needs two valid windows to order them
    n = n.clamp_min(1)
    zc = depths - (depths * v).sum(1, keepdim=True) / n
    dc = (target - (target * v).sum(1, keepdim=True) / n) / unit
    err = (zc - dc.detach()).pow(2) * use
    return err.sum() / use.sum().clamp_min(1)
