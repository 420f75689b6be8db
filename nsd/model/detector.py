r"""Detector B: N windows, one depth and one presence per subject, from the full frame.

The frame (optionally with the background residual :math:`|I - B|` as a fourth
channel, a label-free foreground cue) is resampled to ``input_size`` and
mapped by a small CNN to 6 numbers per window, with NSD's bounded
parametrisation (normalised coordinates, see :mod:`nsd.model.focal_st`):

.. math::
    s = s_{min} + (s_{max} - s_{min})\,\sigma(a_{0:2}), \quad
    t = \beta_{border} \tanh(a_{2:4}), \quad z = a_4, \quad p = \sigma(a_5).

The last layer is zero-initialised with bias :math:`(0.5, 0.5, t^0_i, t^0_i, 0, p^0)`
so every window starts near the centre at scale ~0.70 (0.2 + 0.8 sigma(0.5));
the initial centres :math:`t^0_i` sit on a small circle (``init_spread``) so
that identical windows do not receive identical gradients forever.

Two heads map the CNN features to the 6 numbers per window:

* ``head="mlp"`` (NSD): flatten the feature map, one hidden layer, linear output;
* ``head="attention"``: each window pools the feature map (with two coordinate
  channels) by its own spatial softmax attention, then a shared hidden layer and
  a per-window linear output. The attention-weighted coordinates give the head
  a translation-equivariant path to the window's position, which generalises
  to positions not seen in training better than the flattened map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nsd.model.layers import conv_stack

__all__ = ["Detections", "Detector", "WindowLinear"]


class WindowLinear(nn.Module):
    """One linear layer per window: (B, N, in) -> (B, N, out)."""

    def __init__(self, windows: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(windows, in_features, out_features))
        self.bias = nn.Parameter(torch.zeros(windows * out_features))
        nn.init.kaiming_uniform_(self.weight.view(windows, -1), a=math.sqrt(5))
        self.out_features = out_features

    def forward(self, x: Tensor) -> Tensor:
        b = self.bias.view(-1, self.out_features)
        return torch.einsum("bni,nio->bno", x, self.weight) + b


@dataclass
class Detections:
    """Detector outputs for a batch of frames.

    Attributes:
        boxes: (B, N, 4) = (sx, sy, tx, ty) in normalised coordinates.
        depths: (B, N), smaller is nearer.
        presence: (B, N) in [0, 1] (all ones when presence is disabled).
    """

    boxes: Tensor
    depths: Tensor
    presence: Tensor


class Detector(nn.Module):
    """NSD's detector B.

    Every argument is a ``model.detector`` value of the config (defaults in
    ``conf/model/nsd.yaml`` only; :func:`nsd.model.build.build_model` passes them all).

    Args:
        num_windows: N, the number (or upper bound) of subjects.
        input_size: frames are resampled to (input_size, input_size).
        widths: channels of the strided conv stages.
        hidden: width of the fully connected layer.
        residual_input: add |I - B| (mean over colour) as an input channel.
        min_scale, max_scale: bounds of the window half-size (NSD: 0.2, 1.0).
        border: position bound factor (NSD: 0.8).
        init_spread: radius of the circle of initial window centres.
        presence: learn a presence per window (else presence is 1).
        presence_init: initial presence (before sigmoid inversion).
        head: ``"mlp"`` (NSD) or ``"attention"`` (per-window attention pooling).
    """

    def __init__(
        self,
        num_windows: int,
        input_size: int,
        widths: tuple[int, ...],
        hidden: int,
        residual_input: bool,
        min_scale: float,
        max_scale: float,
        border: float,
        init_spread: float,
        presence: bool,
        presence_init: float,
        head: str,
    ) -> None:
        super().__init__()
        self.num_windows, self.input_size = num_windows, input_size
        self.residual_input, self.use_presence = residual_input, presence
        self.min_scale, self.max_scale, self.border = min_scale, max_scale, border
        if head not in ("mlp", "attention"):
            raise ValueError(f"detector head must be 'mlp' or 'attention', got {head!r}")
        self.head_kind = head
        self.backbone = conv_stack(4 if residual_input else 3, widths)
        feat = input_size // 2 ** len(widths)
        if head == "mlp":
            self.fc = nn.Sequential(
                nn.Flatten(), nn.Linear(widths[-1] * feat * feat, hidden), nn.ReLU(inplace=True)
            )
            self.head = nn.Linear(hidden, num_windows * 6)
        else:
            self.attention = nn.Conv2d(widths[-1] + 2, num_windows, 1)
            self.fc = nn.Sequential(nn.Linear(widths[-1] + 2, hidden), nn.ReLU(inplace=True))
            self.head = WindowLinear(num_windows, hidden, 6)
        nn.init.zeros_(self.head.weight)
        bias = torch.zeros(num_windows, 6)
        bias[:, :2] = 0.5
        for i in range(num_windows):
            a = 2 * math.pi * i / num_windows
            t0 = torch.tensor([math.cos(a), math.sin(a)]) * (init_spread if num_windows > 1 else 0)
            bias[i, 2:4] = torch.atanh(t0 / border)
        bias[:, 5] = math.log(presence_init / (1 - presence_init))
        with torch.no_grad():
            self.head.bias.copy_(bias.reshape(-1))

    def forward(self, images: Tensor, backgrounds: Tensor | None = None) -> Detections:
        """Detect windows.

        Args:
            images: (B, 3, H, W) in [0, 1].
            backgrounds: (B, 3, H, W) median backgrounds (needed with ``residual_input``).
        """
        x = images
        if self.residual_input:
            if backgrounds is None:
                raise ValueError("Detector(residual_input=True) needs the background images")
            x = torch.cat([images, (images - backgrounds).abs().mean(1, keepdim=True)], 1)
        x = F.interpolate(
            x,
            size=(self.input_size, self.input_size),
            mode="bilinear",
            align_corners=False,
            antialias=True,
        )
        f = self.backbone(x)
        if self.head_kind == "mlp":
            a = self.head(self.fc(f)).view(-1, self.num_windows, 6)
        else:
            B, _, h, w = f.shape
            ys = (2 * torch.arange(h, dtype=f.dtype) + 1) / h - 1
            xs = (2 * torch.arange(w, dtype=f.dtype) + 1) / w - 1
            gy, gx = torch.meshgrid(ys, xs, indexing="ij")
            f = torch.cat([f, gx.expand(B, 1, h, w), gy.expand(B, 1, h, w)], 1)
            att = torch.softmax(self.attention(f).flatten(2), -1)  # (B, N, hw)
            pooled = torch.einsum("bnp,bcp->bnc", att, f.flatten(2))  # (B, N, C + 2)
            a = self.head(self.fc(pooled))
        s = self.min_scale + (self.max_scale - self.min_scale) * torch.sigmoid(a[..., 0:2])
        t = self.border * torch.tanh(a[..., 2:4])
        presence = torch.sigmoid(a[..., 5]) if self.use_presence else torch.ones_like(a[..., 5])
        return Detections(torch.cat([s, t], -1), a[..., 4], presence)
