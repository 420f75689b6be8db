"""TODO docstring."""

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
