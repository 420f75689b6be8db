"""Per-window mask normalisation (nsd/model/window_masks.py): known values, invariants, grads."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nsd.core.errors import ConfigError
from nsd.model.bi_nvs import BiNVSConfig
from nsd.model.focal_st import focal_bump
from nsd.model.window_masks import normalise_window_masks


def _edge_mask(size: int = 32) -> torch.Tensor:
    """A mask whose maximum lies on the crop's top row, where the bump is 0 (B=N=C=1)."""
    m = torch.full((1, 1, 1, size, size), 0.02, dtype=torch.float64)
    m[..., 0, :] = 0.9
    return m


def test_max_mode_divides_by_the_maximum():
    m = torch.rand(2, 3, 1, 8, 8, dtype=torch.float64) * 0.5
    out = normalise_window_masks(m, "max", focal=True)
    assert torch.allclose(out, m / m.amax((-2, -1), keepdim=True))
    assert torch.equal(normalise_window_masks(m, "none", focal=True), m)


def test_visible_mode_cannot_hide_the_mask_under_the_bump():
    """The reference max-normalisation leaves a mask hidden at the bump's edge empty once
    pasted; the visible normalisation scales it until its pasted maximum is ~1."""
    m = _edge_mask()
    G = focal_bump(32, 32, dtype=torch.float64)
    pasted_max = (normalise_window_masks(m, "max", focal=True) * G).max().item()
    pasted_visible = (normalise_window_masks(m, "visible", focal=True, pool=1) * G).max().item()
    assert pasted_max < 0.03  # 0.02 / 0.9 at the centre, where G = 1
    assert pasted_visible == pytest.approx(1.0, abs=1e-9)


def test_visible_mode_pooling_spreads_a_narrow_peak():
    """Peak 0.5 with eight neighbours at 0.05 (classical ST, no bump), pool 3: the 3x3
    average is 0.1, so the peak becomes 5 (clamped to 1 by the paste) and the neighbours 0.5."""
    m = torch.zeros(1, 1, 1, 9, 9, dtype=torch.float64)
    m[..., 3:6, 3:6] = 0.05
    m[..., 4, 4] = 0.5
    out = normalise_window_masks(m, "visible", focal=False, pool=3)
    assert out[..., 4, 4].item() == pytest.approx(5.0)
    assert out[..., 3, 3].item() == pytest.approx(0.5)
    assert out[..., 0, 0].item() == 0.0
    # without pooling the same mask is only divided by its maximum
    assert torch.allclose(normalise_window_masks(m, "visible", focal=False, pool=1), m / 0.5)


@settings(max_examples=30, deadline=None)
@given(scale=st.floats(1e-2, 1.0), seed=st.integers(0, 2**16), pool=st.sampled_from([1, 3, 5]))
def test_visible_mode_is_scale_invariant_and_peaks_at_one_once_pasted(scale, seed, pool):
    g = torch.Generator().manual_seed(seed)
    m = torch.rand(2, 2, 1, 16, 16, generator=g, dtype=torch.float64)
    a = normalise_window_masks(m, "visible", focal=True, pool=pool)
    b = normalise_window_masks(m * scale, "visible", focal=True, pool=pool)
    assert torch.allclose(a, b)
    assert a.min() >= 0
    # the bump-weighted (pasted) mask of every window peaks at 1 (pool 1) or above
    peak = (a * focal_bump(16, 16, dtype=torch.float64)).flatten(-3).amax(-1)
    if pool == 1:
        assert torch.allclose(peak, torch.ones_like(peak))
    else:
        assert (peak >= 1 - 1e-12).all()


def test_visible_mode_gradcheck():
    g = torch.Generator().manual_seed(0)
    # random values: unique maxima, so amax is differentiable at the point
    m = (0.05 + 0.1 * torch.rand(1, 2, 1, 8, 8, generator=g, dtype=torch.float64))
    m.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda x: normalise_window_masks(x, "visible", focal=True, pool=3) * 0.5, (m,)
    )


def test_all_zero_masks_stay_zero_and_finite():
    m = torch.zeros(1, 2, 1, 8, 8, requires_grad=True)
    out = normalise_window_masks(m, "visible", focal=True)
    out.sum().backward()
    assert torch.equal(out, torch.zeros_like(out))
    assert torch.isfinite(m.grad).all()


@pytest.mark.parametrize(
    "field, value, match",
    [("mask_normalisation", "median", "mask_normalisation"), ("mask_pool", 4, "mask_pool")],
)
def test_config_errors_name_the_key(field, value, match):
    with pytest.raises(ConfigError, match=match):
        BiNVSConfig.defaults(**{field: value}).validate()
