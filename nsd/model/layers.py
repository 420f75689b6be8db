"""Small building blocks shared by the NSD networks (no pretrained weights exist here)."""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn

__all__ = ["conv_block", "conv_stack", "upsample_block"]


def conv_block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution, GroupNorm (batch-size independent), ReLU."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
        nn.GroupNorm(min(8, c_out), c_out),
        nn.ReLU(inplace=True),
    )


def conv_stack(c_in: int, widths: Sequence[int]) -> nn.Sequential:
    """A strided conv stage per width: each halves the resolution."""
    layers, c = [], c_in
    for w in widths:
        layers += [conv_block(c, w, stride=2), conv_block(w, w)]
        c = w
    return nn.Sequential(*layers)


def upsample_block(c_in: int, c_out: int, convs: int = 2) -> nn.Sequential:
    """Bilinear x2 upsampling then ``convs`` 3x3 convolutions (the NSD decoder's stage)."""
    layers: list[nn.Module] = [nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False)]
    c = c_in
    for _ in range(convs):
        layers.append(conv_block(c, c_out))
        c = c_out
    return nn.Sequential(*layers)
