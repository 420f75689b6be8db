"""SSIM by matrix products against kornia's convolutions (the reference), and its gradient."""

import kornia
import pytest
import torch

from nsd.ops.ssim import reflect_gaussian_matrix, ssim_map


@pytest.mark.parametrize("shape,window", [((2, 3, 32, 32), 7), ((3, 1, 18, 40), 11),
                                          ((1, 3, 9, 13), 7), ((2, 2, 5, 6), 5)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_equals_kornia(shape, window, dtype):
    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(shape, generator=g, dtype=dtype), torch.rand(shape, generator=g, dtype=dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(ssim_map(x, y, window), kornia.metrics.ssim(x, y, window),
                               atol=tol, rtol=0)


def test_gradient_equals_kornia():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 20, 24, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 3, 20, 24, generator=g, dtype=torch.float64)
    (gx,) = torch.autograd.grad(ssim_map(x, y, 7).square().sum(), x)
    (gk,) = torch.autograd.grad(kornia.metrics.ssim(x, y, 7).square().sum(), x)
    torch.testing.assert_close(gx, gk, atol=1e-12, rtol=0)


@pytest.mark.parametrize("grad_x,grad_y", [(True, False), (False, True), (True, True)])
def test_written_out_gradient_equals_autograd_through_kornia(grad_x, grad_y):
    """Each branch of the written-out backward (either image, or both) against kornia."""
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 3, 11, 15, generator=g, dtype=torch.float64, requires_grad=grad_x)
    y = torch.rand(2, 3, 11, 15, generator=g, dtype=torch.float64, requires_grad=grad_y)
    w = torch.rand(2, 3, 11, 15, generator=g, dtype=torch.float64)
    inputs = [t for t in (x, y) if t.requires_grad]
    ours = torch.autograd.grad((ssim_map(x, y, 7) * w).sum(), inputs)
    ref = torch.autograd.grad((kornia.metrics.ssim(x, y, 7) * w).sum(), inputs)
    for a, b in zip(ours, ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_gradcheck():
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 2, 6, 7, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(1, 2, 6, 7, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: ssim_map(a, b, 5), (x, y))


def test_known_values():
    x = torch.rand(1, 3, 16, 16, dtype=torch.float64)
    torch.testing.assert_close(ssim_map(x, x), torch.ones_like(x), atol=1e-9, rtol=0)
    # flat images a and b: only the luminance term, (2ab + c1) / (a^2 + b^2 + c1)
    a, b, c1 = 0.2, 0.6, 1e-4
    out = ssim_map(torch.full((1, 1, 8, 8), a, dtype=torch.float64),
                   torch.full((1, 1, 8, 8), b, dtype=torch.float64), 7, eps=0.0)
    torch.testing.assert_close(out, torch.full_like(out, (2 * a * b + c1) / (a * a + b * b + c1)))
    # anti-correlated images score below 0
    assert ssim_map(x, 1 - x).mean() < 0


def test_matrix_is_the_reflect_padded_gaussian():
    m = reflect_gaussian_matrix(10, 5, torch.float64)
    torch.testing.assert_close(m.sum(1), torch.ones(10, dtype=torch.float64))
    taps = kornia.filters.get_gaussian_kernel1d(5, 1.5, dtype=torch.float64).reshape(-1)
    torch.testing.assert_close(m[4, 2:7], taps)  # an interior row: the taps, centred
    assert m[4, :2].abs().sum() == 0 and m[4, 7:].abs().sum() == 0
    # row 0 under reflect padding: v[-2], v[-1] are v[2], v[1]
    row0 = torch.stack([taps[2], taps[1] + taps[3], taps[0] + taps[4]])
    torch.testing.assert_close(m[0, :3], row0)


@pytest.mark.parametrize("size,window", [(3, 7), (8, 4), (8, 0)])
def test_bad_sizes_raise(size, window):
    with pytest.raises(ValueError, match="window"):
        reflect_gaussian_matrix(size, window)


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match="one shape"):
        ssim_map(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))
