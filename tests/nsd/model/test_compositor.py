"""The erf-transmittance compositor against a slow reference, its worked cases and limits."""

from __future__ import annotations

import math

import pytest
import torch

from nsd.model.compositor import additive_composite, blend, erf_transmittance_composite
from tests.base import DTYPES, BaseTester


def reference_composite(masks, depths):
    """Obviously-correct per-pixel loops over NSD eq. 7 (transmittance integral in closed form)."""
    B, N, H, W = masks.shape
    weights = torch.zeros_like(masks)
    bg = torch.zeros(B, H, W, dtype=masks.dtype)
    for b in range(B):
        for y in range(H):
            for x in range(W):
                S = masks[b, :, y, x]

                def T(z, S=S, b=b):
                    total = 0.0
                    for i in range(N):
                        total = total + S[i] * (torch.erf(z - depths[b, i]) + 1)
                    return torch.exp(-total)

                t_inf = torch.exp(-2 * S.sum())
                vis = torch.stack([T(depths[b, j]) * S[j] for j in range(N)])
                Z = (1 - t_inf) / vis.sum()
                weights[b, :, y, x] = vis * Z
                bg[b, y, x] = t_inf
    return weights, bg


def _random(B=2, N=3, H=4, W=5, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    masks = torch.rand(B, N, H, W, generator=g, dtype=dtype) * 0.9 + 0.05
    depths = torch.randn(B, N, generator=g, dtype=dtype) * 1.5
    return masks, depths


class TestErfTransmittance(BaseTester):
    @DTYPES
    def test_matches_reference_outputs(self, dtype):
        masks, depths = _random(dtype=dtype)
        c = erf_transmittance_composite(masks, depths)
        ref_w, ref_bg = reference_composite(masks, depths)
        self.assert_close(c.weights, ref_w)
        self.assert_close(c.background_weight, ref_bg)

    def test_matches_reference_gradients(self):
        masks, depths = _random(B=1, N=3, H=2, W=3)
        masks.requires_grad_(True)
        depths.requires_grad_(True)
        layers = torch.rand(1, 3, 3, 2, 3, dtype=torch.float64)
        bgimg = torch.rand(1, 3, 2, 3, dtype=torch.float64)

        def image(weights, bgw):
            return ((weights.unsqueeze(2) * layers).sum(1) + bgw.unsqueeze(1) * bgimg).pow(2).sum()

        c = erf_transmittance_composite(masks, depths)
        g_fast = torch.autograd.grad(image(c.weights, c.background_weight), (masks, depths))
        ref_w, ref_bg = reference_composite(masks, depths)
        g_ref = torch.autograd.grad(image(ref_w, ref_bg), (masks, depths))
        for a, b in zip(g_fast, g_ref, strict=True):
            self.assert_close(a, b)

    def test_gradcheck(self):
        masks, depths = _random(B=1, N=3, H=2, W=2)
        assert self.gradcheck(
            lambda m, z: erf_transmittance_composite(m, z).weights, [masks, depths]
        )
        assert self.gradcheck(lambda m, z: erf_transmittance_composite(m, z).depth, [masks, depths])

    def test_one_opaque_subject_leaks_e_minus_2(self):
        c = erf_transmittance_composite(torch.ones(1, 1, 1, 1), torch.zeros(1, 1))
        self.assert_close(c.background_weight, torch.full((1, 1, 1), math.exp(-2)))
        self.assert_close(c.weights, torch.full((1, 1, 1, 1), 1 - math.exp(-2)))

    def test_two_opaque_subjects_worked_case(self):
        masks = torch.ones(1, 2, 1, 1, dtype=torch.float64)
        c = erf_transmittance_composite(masks, torch.tensor([[0.0, 3.0]], dtype=torch.float64))
        w = c.weights.flatten()
        assert w[0].item() == pytest.approx(0.8647, abs=5e-4)  # "~0.86"
        assert w[1].item() == pytest.approx(0.1170, abs=5e-4)  # "~0.12"
        assert c.background_weight.item() == pytest.approx(math.exp(-4), rel=1e-9)
        swapped = erf_transmittance_composite(
            masks, torch.tensor([[3.0, 0.0]], dtype=torch.float64)
        )
        self.assert_close(swapped.weights.flatten(), w.flip(0))

    @DTYPES
    def test_partition_of_unity(self, dtype):
        masks, depths = _random(B=3, N=4, H=6, W=6, dtype=dtype, seed=3)
        c = erf_transmittance_composite(masks, depths)
        self.assert_close(c.weights.sum(1) + c.background_weight, torch.ones(3, 6, 6, dtype=dtype))
        # the background weight is T(inf) (the normalisation never needs its clamp here)
        self.assert_close(c.background_weight, torch.exp(-2 * masks.sum(1)))
        assert (c.weights >= 0).all()

    def test_nearer_subject_dominates_overlap(self):
        masks = torch.ones(1, 2, 1, 1) * 0.9
        near_first = erf_transmittance_composite(masks, torch.tensor([[-2.0, 2.0]]))
        assert near_first.weights[0, 0] > 5 * near_first.weights[0, 1]

    def test_depth_map_and_blend(self):
        masks = torch.zeros(1, 2, 1, 2)
        masks[0, 0, 0, 0] = 1.0  # subject 0 alone at pixel 0
        masks[0, 1, 0, 1] = 1.0  # subject 1 alone at pixel 1
        c = erf_transmittance_composite(masks, torch.tensor([[1.5, 4.0]]))
        self.assert_close(c.depth, torch.tensor([[[1.5, 4.0]]]))
        layers = torch.zeros(1, 2, 3, 1, 2)
        layers[0, 0] = 1.0
        img = blend(c, layers, torch.zeros(1, 3, 1, 2))
        self.assert_close(img[0, :, 0, 0], torch.full((3,), 1 - math.exp(-2)))
        self.assert_close(img[0, :, 0, 1], torch.zeros(3))

    def test_transparent_subjects_show_background(self):
        c = erf_transmittance_composite(torch.zeros(2, 3, 4, 4), torch.randn(2, 3))
        assert torch.equal(c.background_weight, torch.ones(2, 4, 4))
        assert torch.equal(c.weights, torch.zeros(2, 3, 4, 4))

    def test_bad_shapes(self):
        with pytest.raises(ValueError, match=r"depths must be \(B, N\)"):
            erf_transmittance_composite(torch.ones(1, 2, 3, 3), torch.zeros(1, 3))
        with pytest.raises(ValueError, match=r"masks must be \(B, N, H, W\)"):
            erf_transmittance_composite(torch.ones(2, 3, 3), torch.zeros(2, 3))


class TestAdditive(BaseTester):
    def test_blends_without_depth(self):
        masks = torch.ones(1, 2, 1, 1) * 0.75
        c = additive_composite(masks, torch.tensor([[0.0, 9.0]]))
        self.assert_close(c.weights.flatten(), torch.tensor([0.5, 0.5]))  # no occlusion
        self.assert_close(c.background_weight, torch.zeros(1, 1, 1))
        single = additive_composite(torch.ones(1, 1, 1, 1) * 0.3, torch.zeros(1, 1))
        self.assert_close(single.background_weight, torch.full((1, 1, 1), 0.7))


class TestSkippingOcclusion(BaseTester):
    def test_separate_equals_erf_without_overlap(self):
        from nsd.model.compositor import masks_overlap, separate_composite

        g = torch.Generator().manual_seed(5)
        owner = torch.randint(-1, 3, (2, 6, 7), generator=g)
        masks = torch.stack([(owner == j).double() for j in range(3)], 1)
        masks = masks * torch.rand(masks.shape, generator=g, dtype=torch.float64)
        depths = torch.randn(2, 3, generator=g, dtype=torch.float64)
        assert not masks_overlap(masks).any()
        fast, full = separate_composite(masks, depths), erf_transmittance_composite(masks, depths)
        self.assert_close(fast.weights, full.weights)
        self.assert_close(fast.background_weight, full.background_weight)
        masks[0, 1, 0, 0] = masks[0, 0, 0, 0] = 0.5
        assert masks_overlap(masks).tolist() == [True, False]
