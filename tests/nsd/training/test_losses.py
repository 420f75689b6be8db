"""The image loss terms (nsd/training/losses.py): known values and the two-view batch."""

import pytest
import torch

from nsd.training.losses import pixel_loss, total_image_loss


def test_pixel_loss_known_values():
    pred, target = torch.zeros(1, 3, 1, 2), torch.ones(1, 3, 1, 2)
    pred[..., 1] = 1  # errors 1 and 0
    assert pixel_loss(pred, target).item() == pytest.approx(0.5)
    weight = torch.tensor([[[3.0, 1.0]]])
    assert pixel_loss(pred, target, weight).item() == pytest.approx(3 / 4)


@pytest.mark.parametrize("renormalise,weighted", [(False, True), (True, False), (True, True)])
def test_parts_average_the_parts_losses(renormalise, weighted):
    """Two views stacked with ``parts=2``: each view's weighted pixel loss normalised on its
    own, then averaged, as two separate calls give (the weights' sums differ per view)."""
    g = torch.Generator().manual_seed(0)
    pred, target = torch.rand(2, 2, 4, 3, 9, 11, generator=g, dtype=torch.float64)
    weight = torch.rand(2, 4, 9, 11, generator=g, dtype=torch.float64) if weighted else None
    weight = None if weight is None else weight * torch.tensor([1.0, 5.0]).view(2, 1, 1, 1)
    both = total_image_loss(pred.flatten(0, 1), target.flatten(0, 1),
                            None if weight is None else weight.flatten(0, 1), 1.0, 7,
                            renormalise, parts=2)
    one = [total_image_loss(pred[i], target[i], None if weight is None else weight[i], 1.0, 7,
                            renormalise) for i in range(2)]
    for k in ("pixel", "ssim"):
        torch.testing.assert_close(both[k], (one[0][k] + one[1][k]) / 2, rtol=0, atol=1e-14)
    if weighted:  # one normalisation over both views would differ
        pooled = total_image_loss(pred.flatten(0, 1), target.flatten(0, 1), weight.flatten(0, 1),
                                  1.0, 7, renormalise)
        assert abs(pooled["pixel"] - both["pixel"]) > 1e-4
