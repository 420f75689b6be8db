r"""Weak priors on the detector's windows (NSD sec. 3.4) and on window presence.

All priors act on *batch means per window*, never on single detections: a
per-sample prior is "too easy to fulfil with opposing positions" and would
bias every detection to the centre. For window :math:`i` over a batch of
:math:`B` images with boxes :math:`(s_x, s_y, t_x, t_y)`:

.. math::
    L_{pos} = \frac1N \sum_i \big\| \bar t_i \big\|^2, \qquad
    L_{scale} = \frac1N \sum_i \big(\bar s_i - s^*\big)^2, \qquad
    L_{aspect} = \frac1N \sum_i \big(\overline{\log r_i} - \log r^*\big)^2,

with :math:`\bar x_i` the batch mean, :math:`s = (s_x + s_y)/2` (0.4 in NSD),
and :math:`r = (s_y H)/(s_x W)` the window's height/width ratio in pixels (1.5
in NSD: people are taller than wide; a quadruped scene wants about 0.6).

The presence prior (our extension for scenes with fewer individuals than
windows) is the mean presence, an L1 pressure towards fewer active windows:
:math:`L_{presence} = \frac{1}{BN}\sum_{b,i} p_{b,i}`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["aspect_prior", "position_prior", "presence_prior", "scale_prior"]


def position_prior(boxes: Tensor) -> Tensor:
    """Squared distance of each window's batch-mean centre from the image centre.

    Args:
        boxes: (B, N, 4) = (sx, sy, tx, ty).
    """
    return boxes[..., 2:].mean(0).pow(2).sum(-1).mean()


def scale_prior(boxes: Tensor, target: float = 0.4) -> Tensor:
    """Squared deviation of each window's batch-mean scale from ``target``."""
    s = boxes[..., :2].mean(-1)
    return (s.mean(0) - target).pow(2).mean()


def aspect_prior(boxes: Tensor, ratio: float = 1.5, image_size: tuple[int, int] = (1, 1)) -> Tensor:
    """Squared deviation of each window's batch-mean log aspect (height/width) from log ``ratio``.

    Args:
        boxes: (B, N, 4).
        ratio: preferred height / width in pixels.
        image_size: (H, W), to measure the ratio in pixels.
    """
    H, W = image_size
    log_r = torch.log(boxes[..., 1] * H) - torch.log(boxes[..., 0] * W)
    return (log_r.mean(0) - math.log(ratio)).pow(2).mean()


def presence_prior(presence: Tensor) -> Tensor:
    """Mean window presence (B, N) in [0, 1]: prefers fewer active windows."""
    return presence.mean()
