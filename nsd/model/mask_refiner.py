r"""The mask refiner (ours): each decoded window mask sharpened by the target window's own pixels.

Off by default (``model.mask_refiner.widths=[]``): with it NSD's own masks are sharp, but the
exported masks and the keypoints were a little worse (docs/nsd.md, "The mask refiner").

NSD decodes a window's mask from its 3D latent cloud and appearance vector alone. After a
few thousand steps on this machine the decoded masks are the shape of an average pose, a
blob without limbs (raw composited mIoU 0.36-0.38 on the default scene; 0.64 with the refiner
and the hull mask prior, docs/nsd.md), while
the target view's own pixels show every limb. The refiner is a small convolutional network
that sees, per window of the *target* view, the image crop :math:`c`, the background crop
:math:`b` (both through the same transformer as the encoder's input) and what was decoded
for that window, colour :math:`\hat I` and mask :math:`\hat m`, and corrects the mask in the
logit domain:

.. math::
    m = \sigma\big(\operatorname{logit}(\hat m) + g(f([c, b, \hat I, \hat m]))\big),
    \qquad g(x) = x \ (x \le 0), \quad g(x) = G \tanh(x / G) \ (x > 0).

:math:`g` (optional, ``grow`` :math:`= G`; off by default) lets the refiner carve a decoded
mask freely but grow it by at most :math:`G` logits: a pixel becomes the window's
(:math:`m > 0.5`) only where the decoder put at least :math:`\sigma(-G)` (5 % for
:math:`G = 3`). It was meant to keep a window that the detector places over two individuals
from claiming both, as an unbounded refiner does; measured, it did not (docs/nsd.md, "The mask
refiner"). :math:`g` is continuous with its first derivative at 0.

The last layer of :math:`f` starts at zero, so an untrained refiner returns the decoded mask
(up to the clamp of :math:`\hat m` to :math:`[\epsilon, 1 - \epsilon]`). It learns from what
trains the masks anyway, with no labels: the re-synthesis loss (a pixel is this window's if
its colour is what the window decoded there, and this holds across views, where the colours
come from the other camera), the foreground coverage prior (the windows' union covers the
background residual) and the hull mask prior (:mod:`nsd.priors.mask`: who owns a pixel;
``prior_mask=hull prior_mask.weight=4``, which it needs). It never changes the colours, so
the re-synthesised colours still come from the source view's latent and appearance only.
Windows keep the mask normalisation of :mod:`nsd.model.window_masks` after the refiner, so it
cannot switch a window off.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor, nn

from nsd.model.layers import conv_block

__all__ = ["MaskRefiner"]

LOGIT_CLAMP = 1e-4  # the decoded mask is clamped to [eps, 1 - eps] before its logit


class MaskRefiner(nn.Module):
    """Refined window mask logits from the target window's crops and the decoded window.

    A U-shaped stack: ``widths[0]`` channels at the crop's resolution, one strided stage per
    further width, bilinear upsampling back with a skip connection, and a 1 x 1 output
    convolution that starts at zero.

    Args:
        widths: channels per resolution, finest first (at least one).
        grow: :math:`G`, the most logits the refiner may add to a decoded mask (None: no bound).
    """

    IN_CHANNELS = 10  # image crop 3, background crop 3, decoded colour 3, decoded mask 1

    def __init__(self, widths: tuple[int, ...], grow: float | None = None) -> None:
        super().__init__()
        if not widths:
            raise ValueError("MaskRefiner needs at least one width")
        if grow is not None and not grow > 0:
            raise ValueError(f"MaskRefiner's grow must be > 0 or None, got {grow}")
        self.grow = grow
        self.inp = conv_block(self.IN_CHANNELS, widths[0])
        self.down = nn.ModuleList(
            [conv_block(a, b, stride=2) for a, b in itertools.pairwise(widths)]
        )
        self.up = nn.ModuleList(
            [conv_block(fine + coarse, fine) for fine, coarse in itertools.pairwise(widths)][::-1]
        )
        self.out = nn.Conv2d(widths[0], 1, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, crops: Tensor, backgrounds: Tensor, rgb: Tensor, mask: Tensor) -> Tensor:
        """Refined mask logits (B, N, 1, h, w).

        Args:
            crops, backgrounds: the target windows' image and background crops (B, N, 3, h, w).
            rgb: the decoded colours in the target windows' slots (B, N, 3, h, w).
            mask: the decoded masks in those slots (B, N, 1, h, w), non-negative.
        """
        B, N = mask.shape[:2]
        x = torch.cat([crops, backgrounds, rgb, mask], 2).flatten(0, 1)
        skips = [self.inp(x)]
        for stage in self.down:
            skips.append(stage(skips[-1]))
        y = skips.pop()
        for stage in self.up:
            skip = skips.pop()
            y = nn.functional.interpolate(y, size=skip.shape[-2:], mode="bilinear",
                                          align_corners=False)
            y = stage(torch.cat([y, skip], 1))
        delta = self.out(y).view(B, N, 1, *mask.shape[-2:])
        if self.grow is not None:
            delta = torch.where(delta > 0, self.grow * torch.tanh(delta / self.grow), delta)
        return torch.logit(mask.clamp(LOGIT_CLAMP, 1 - LOGIT_CLAMP)) + delta
