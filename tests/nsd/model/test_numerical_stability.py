"""Numerical stability at the extremes: finite values, correct limits, finite gradients.

Property-based (hypothesis) and targeted cases for the compositor, the
appearance association, the focal / inverse spatial transformers with the
detector's bounded boxes, the NNOPCS normalisation and the keypoint renderer.
The training loop at extreme configs is in ``test_nsd_train_extremes.py``.
Each case that produced NaN/Inf or a wrong limit before its fix says so.
"""

from __future__ import annotations

import dataclasses
import math

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nsd.model.association import (
    appearance_similarity,
    apply_association,
    association_softmax,
    hard_association,
)
from nsd.model.compositor import additive_composite, blend, erf_transmittance_composite
from nsd.model.detector import Detector
from nsd.model.focal_st import crop, focal_bump_at, inverse_theta, paste
from nsd.synth.nnopcs import canonical_points, nnopcs_bounds, nnopcs_of
from nsd.synth.skeleton import BIPED
from tests.base import DTYPES, BaseTester
from tests.nsd.model.test_compositor import reference_composite

PROPERTY = settings(max_examples=60, deadline=None, derandomize=True)


def _finite(*tensors: torch.Tensor) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def _grads(outputs: torch.Tensor, inputs, seed: int = 0):
    """Gradients of a fixed random linear functional of ``outputs``."""
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(outputs.shape, generator=g, dtype=torch.float64).to(outputs.dtype)
    return torch.autograd.grad((outputs * w).sum(), inputs, allow_unused=True)


# ---------------------------------------------------------------------------- compositor
MASK_VALUES = st.one_of(st.just(0.0), st.just(1.0), st.floats(0.0, 1.0, width=32))
DEPTH_VALUES = st.one_of(st.just(0.0), st.just(1e4), st.just(-1e4), st.floats(-1e4, 1e4, width=32))


@st.composite
def layer_stacks(draw):
    """(masks (1, N, 2, 3), depths (1, N)) as float64 holding float32-exact values."""
    n = draw(st.integers(1, 8))
    masks = draw(hnp.arrays(np.float64, (1, n, 2, 3), elements=MASK_VALUES))
    depths = draw(hnp.arrays(np.float64, (1, n), elements=DEPTH_VALUES))
    if draw(st.booleans()):  # exactly equal depths
        depths[:] = depths[0, 0]
    if draw(st.booleans()):  # a pixel where every subject is fully transparent
        masks[..., 0, 0] = 0.0
    return torch.from_numpy(masks), torch.from_numpy(depths)


def _composite_with_grads(masks, depths, dtype):
    m = masks.to(dtype).requires_grad_(True)
    z = depths.to(dtype).requires_grad_(True)
    c = erf_transmittance_composite(m, z)
    layers = torch.linspace(0, 1, m.shape[1], dtype=dtype)[None, :, None, None, None]
    background = torch.full((1, 3, *m.shape[2:]), 0.3, dtype=dtype)
    image = blend(c, layers.expand(*m.shape[:2], 3, *m.shape[2:]), background)
    gm, gz = torch.autograd.grad(image.pow(2).sum() + c.weights.sum(), (m, z))
    return c, gm, gz


class TestCompositorExtremes(BaseTester):
    @PROPERTY
    @given(layer_stacks())
    def test_property_finite_partition_and_dtypes_agree(self, stack):
        masks, depths = stack
        c64, gm64, gz64 = _composite_with_grads(masks, depths, torch.float64)
        c32, gm32, gz32 = _composite_with_grads(masks, depths, torch.float32)
        for c, gm, gz in ((c64, gm64, gz64), (c32, gm32, gz32)):
            assert _finite(c.weights, c.background_weight, c.depth, gm, gz)
            assert (c.weights >= 0).all() and (c.weights <= 1 + 1e-6).all()
            self.assert_close(
                c.weights.sum(1) + c.background_weight, torch.ones_like(c.background_weight)
            )
            # the background weight is T(inf) = exp(-2 sum S) everywhere, also where S = 0
            self.assert_close(c.background_weight, torch.exp(-2 * masks.sum(1)).to(c.weights.dtype))
        self.assert_close(c32.weights.double(), c64.weights, rtol=1e-4, atol=1e-5)
        for g32, g64 in ((gm32, gm64), (gz32, gz64)):
            scale = float(g64.abs().max()) + 1.0
            self.assert_close(g32.double(), g64, rtol=1e-3, atol=1e-4 * scale)

    @PROPERTY
    @given(layer_stacks())
    def test_property_matches_reference_where_defined(self, stack):
        masks, depths = stack
        c = erf_transmittance_composite(masks, depths)
        ref_w, ref_bg = reference_composite(masks, depths)
        covered = masks.sum(1, keepdim=True) > 0  # the reference divides 0 by 0 elsewhere
        self.assert_close(torch.where(covered, c.weights, 0), torch.where(covered, ref_w, 0))
        self.assert_close(c.background_weight, torch.where(covered[:, 0], ref_bg, 1.0))

    @DTYPES
    @pytest.mark.parametrize("n", [1, 2, 5, 8])
    def test_all_transparent_limit_values_and_gradients(self, n, dtype):
        """Fixed: the clamped 0/0 gave a zero gradient here; the limit is dw_j/dS_j = 2."""
        masks = torch.zeros(2, n, 3, 3, dtype=dtype, requires_grad=True)
        depths = torch.linspace(-1e4, 1e4, n, dtype=dtype).expand(2, n).clone().requires_grad_()
        c = erf_transmittance_composite(masks, depths)
        assert torch.equal(c.weights, torch.zeros_like(c.weights))
        assert torch.equal(c.background_weight, torch.ones_like(c.background_weight))
        assert torch.equal(c.depth, torch.zeros_like(c.depth))
        jac = torch.autograd.grad(c.weights[:, 0].sum(), masks, retain_graph=True)[0]
        expected = torch.zeros_like(jac)
        expected[:, 0] = 2.0  # w_j ~ 2 S_j: T = 1 and 1 - T(inf) ~ 2 sum S
        assert torch.equal(jac, expected)
        gz = torch.autograd.grad(c.weights.sum(), depths)[0]
        assert torch.equal(gz, torch.zeros_like(gz))

    @DTYPES
    def test_gradient_is_continuous_at_zero_mass(self, dtype):
        def jacobian_diag(scale):
            m = torch.full((1, 3, 1, 1), scale, dtype=dtype, requires_grad=True)
            c = erf_transmittance_composite(m, torch.tensor([[0.0, 0.5, 3.0]], dtype=dtype))
            return torch.stack(
                [
                    torch.autograd.grad(c.weights[0, j].sum(), m, retain_graph=True)[0][0, j, 0, 0]
                    for j in range(3)
                ]
            )

        at_zero = jacobian_diag(0.0)
        for s in (1e-30, 1e-12, 1e-6):
            self.assert_close(jacobian_diag(s), at_zero, rtol=1e-4, atol=1e-4)
        # across the power-series / closed-form switch of phi (mass 1e-2)
        switch = 0.01 / 3
        self.assert_close(
            jacobian_diag(switch * (1 - 1e-6)),
            jacobian_diag(switch * (1 + 1e-6)),
            rtol=1e-4,
            atol=1e-5,
        )

    def test_gradcheck_at_zero_and_tiny_masks(self):
        depths = torch.tensor([[0.0, 0.7]], dtype=torch.float64)
        for scale in (0.0, 1e-3):
            masks = torch.full((1, 2, 1, 2), scale, dtype=torch.float64)
            assert self.gradcheck(lambda m: erf_transmittance_composite(m, depths).weights, [masks])

    @DTYPES
    @pytest.mark.parametrize("n", [1, 2, 8])
    def test_opaque_layers_far_apart_and_equal(self, n, dtype):
        masks = torch.ones(1, n, 1, 1, dtype=dtype, requires_grad=True)
        far = (torch.arange(n, dtype=dtype) * 1e4)[None].requires_grad_()
        c = erf_transmittance_composite(masks, far)
        # layers far apart: layer j sees its own half plus every nearer layer whole
        visible = torch.exp(-(1 + 2 * torch.arange(n, dtype=torch.float64)))
        expected = visible * -math.expm1(-2 * n) / visible.sum()
        self.assert_close(c.weights.flatten().double(), expected, rtol=1e-5, atol=1e-7)
        depth = (expected * far.detach().double()[0]).sum() / expected.sum()
        self.assert_close(c.depth.double().flatten(), depth.reshape(1), rtol=1e-5, atol=1e-3)
        gm, gz = _grads(c.weights, (masks, far))
        assert _finite(gm, gz)
        assert torch.equal(gz, torch.zeros_like(gz))  # erf is flat 1e4 away
        equal = erf_transmittance_composite(masks, torch.zeros(1, n, dtype=dtype))
        self.assert_close(
            equal.weights.flatten(), torch.full((n,), -math.expm1(-2 * n) / n, dtype=dtype)
        )
        self.assert_close(
            equal.background_weight.flatten(), torch.tensor([math.exp(-2 * n)], dtype=dtype)
        )

    @DTYPES
    def test_additive_compositor_limits(self, dtype):
        masks = torch.zeros(1, 3, 2, 2, dtype=dtype, requires_grad=True)
        c = additive_composite(masks, torch.zeros(1, 3, dtype=dtype))
        assert torch.equal(c.background_weight, torch.ones_like(c.background_weight))
        jac = torch.autograd.grad(c.weights[:, 0].sum(), masks)[0]
        assert torch.equal(jac[:, 0], torch.ones_like(jac[:, 0]))
        full = additive_composite(
            torch.ones(1, 8, 1, 1, dtype=dtype), torch.zeros(1, 8, dtype=dtype)
        )
        self.assert_close(full.weights.flatten(), torch.full((8,), 1 / 8, dtype=dtype))


# ---------------------------------------------------------------------------- association
class TestAssociationExtremes(BaseTester):
    @DTYPES
    @pytest.mark.parametrize("beta", [0.1, 1.0, 10.0, 1e3])
    def test_zero_appearance_gives_uniform_association(self, beta, dtype):
        a = torch.zeros(2, 3, 32, dtype=dtype, requires_grad=True)
        b = torch.zeros(2, 4, 32, dtype=dtype, requires_grad=True)
        M = appearance_similarity(a, b)
        A = association_softmax(M, beta)
        assert torch.equal(M, torch.zeros_like(M))
        self.assert_close(A, torch.full_like(A, 0.25))
        ga, gb = _grads(A, (a, b))
        assert _finite(ga, gb)

    @DTYPES
    @pytest.mark.parametrize("beta", [0.1, 10.0, 1e3])
    def test_identical_appearances(self, beta, dtype):
        a = torch.linspace(-1, 2, 32, dtype=dtype).expand(1, 3, 32).clone().requires_grad_()
        M = appearance_similarity(a, a)
        norm2 = float((a.detach()[0, 0, :16].double() ** 2).sum())
        self.assert_close(M, torch.full_like(M, norm2 / (norm2 + 1e-4)))
        A = association_softmax(M, beta)
        self.assert_close(A, torch.full_like(A, 1 / 3))
        assert _finite(*_grads(A, (a,)))

    @PROPERTY
    @given(
        log_beta=st.floats(math.log10(0.1), 3.0),
        log_scale=st.floats(-30.0, 30.0),
        zero_rows=st.integers(0, 3),
        seed=st.integers(0, 2**16),
    )
    def test_property_finite_rows_sum_to_one(self, log_beta, log_scale, zero_rows, seed):
        """Fixed: vectors of magnitude ~1e19 overflowed float32 to inf / inf = NaN."""
        g = torch.Generator().manual_seed(seed)
        a = torch.randn(1, 3, 24, generator=g) * 10.0**log_scale
        b = torch.randn(1, 3, 24, generator=g) * 10.0**log_scale
        a[:, :zero_rows] = 0
        a.requires_grad_(True)
        b.requires_grad_(True)
        M = appearance_similarity(a, b)
        A = association_softmax(M, 10.0**log_beta)
        assert _finite(M, A, *_grads(A, (a, b), seed))
        assert (M.abs() <= 1 + 1e-6).all()
        self.assert_close(A.sum(-1), torch.ones(1, 3))
        # magnitude does not matter once the norms dwarf eps (float64 reference)
        if log_scale > 1:
            ref = torch.nn.functional.cosine_similarity(
                a.detach().double()[:, :, None, :16], b.detach().double()[:, None, :, :16], -1
            )
            nonzero = a.detach()[:, :, None, :16].abs().sum(-1) > 0
            self.assert_close(
                torch.where(nonzero, M.double(), 0),
                torch.where(nonzero, ref, 0),
                rtol=1e-5,
                atol=1e-6,
            )

    def test_large_beta_is_the_hard_association(self):
        a = torch.eye(4, 16)[None]
        b = torch.eye(4, 16)[None].flip(1)
        M = appearance_similarity(a, b)
        soft = association_softmax(M, 1e3)
        self.assert_close(soft, hard_association(M))
        windows = torch.arange(4.0).view(1, 4, 1)
        self.assert_close(apply_association(soft, windows).flatten(), torch.tensor([3.0, 2, 1, 0]))


# ---------------------------------------------------------------------------- spatial transformers
def _ramp(dtype=torch.float64, H=6, W=8):
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij"
    )
    return torch.stack([xs, ys, xs + ys])[None] / 10  # (1, 3, H, W), linear in x and y


class TestSpatialTransformerExtremes(BaseTester):
    @DTYPES
    @pytest.mark.parametrize(
        "box",
        [
            [0.2, 0.2, 0.0, 0.0],  # smallest window
            [1.0, 1.0, 0.0, 0.0],  # the whole frame
            [0.2, 1.0, 0.8, -0.8],  # scale and position bounds together
            [1.0, 1.0, 0.8, 0.8],  # partly outside the frame
            [0.5, 0.5, 3.0, -3.0],  # fully outside the frame
            [1.0, 0.2, -40.0, 0.0],  # far outside
        ],
    )
    @pytest.mark.parametrize("size", [(1, 1), (2, 2), (16, 16)])
    @pytest.mark.parametrize("focal", [True, False])
    def test_crop_and_paste_finite(self, box, size, focal, dtype):
        image = _ramp(dtype).requires_grad_(True)
        boxes = torch.tensor([[box]], dtype=dtype, requires_grad=True)
        crops = crop(image, boxes, size, focal=focal)
        assert _finite(crops, *_grads(crops, (image, boxes)))
        windows = torch.rand(1, 1, 1, *size, dtype=dtype, requires_grad=True)
        layer = paste(windows, boxes, (6, 8), focal=focal)
        assert _finite(layer, *_grads(layer, (windows, boxes)))
        assert (layer >= 0).all() and (layer <= 1).all()  # a mask stays a mask
        if abs(box[2]) - box[0] >= 1 or abs(box[3]) - box[1] >= 1:  # fully outside
            assert torch.equal(crops, torch.zeros_like(crops))
            assert torch.equal(layer, torch.zeros_like(layer))

    @DTYPES
    def test_identity_box_is_the_image(self, dtype):
        image = _ramp(dtype)
        box = torch.tensor([[[1.0, 1.0, 0.0, 0.0]]], dtype=dtype)
        crops = crop(image, box, (6, 8), focal=False)
        self.assert_close(crops[:, 0], image)
        self.assert_close(paste(crops, box, (6, 8), focal=False)[:, 0], image)

    @DTYPES
    def test_one_pixel_crop_samples_the_box_centre(self, dtype):
        image = _ramp(dtype)  # channel 0 is x / 10 at pixel centres
        for tx, ty in ((0.0, 0.0), (0.5, -0.25), (-0.8, 0.8)):
            boxes = torch.tensor([[[0.2, 0.2, tx, ty]]], dtype=dtype, requires_grad=True)
            c = crop(image, boxes, (1, 1), focal=True)  # the bump is 1 at the centre
            x_pix, y_pix = (tx + 1) * 8 / 2 - 0.5, (ty + 1) * 6 / 2 - 0.5
            self.assert_close(
                c.flatten(), torch.tensor([x_pix, y_pix, x_pix + y_pix], dtype=dtype) / 10
            )
            (g,) = torch.autograd.grad(c[0, 0, 0].sum(), boxes)
            self.assert_close(g[0, 0, 2], torch.tensor(8 / 2 / 10, dtype=dtype))  # d x / d tx

    def test_partly_outside_pads_with_zeros_or_border(self):
        image = torch.ones(1, 1, 4, 4, dtype=torch.float64)
        box = torch.tensor([[[1.0, 1.0, 1.0, 0.0]]], dtype=torch.float64)  # right half outside
        zeros = crop(image, box, (4, 4), focal=False)
        border = crop(image, box, (4, 4), focal=False, padding_mode="border")
        self.assert_close(zeros[0, 0, 0, :, :2], torch.ones(4, 2, dtype=torch.float64))
        self.assert_close(zeros[0, 0, 0, :, 3], torch.zeros(4, dtype=torch.float64))
        self.assert_close(border, torch.ones_like(border))

    @DTYPES
    def test_detector_bounds_at_saturated_logits(self, dtype):
        det = Detector(
            num_windows=3, input_size=16, widths=(4, 4), hidden=8, residual_input=True,
            min_scale=0.2, max_scale=1.0, border=0.8, init_spread=0.1, presence=False,
            presence_init=0.95, head="mlp",
        ).to(dtype)
        with torch.no_grad():
            det.head.bias.copy_(torch.tensor([1e4, -1e4, 1e4, -1e4, 1e4, 0.0] * 3, dtype=dtype))
        images = torch.rand(2, 3, 12, 16, dtype=dtype)
        out = det(images, images.flip(-1))
        sx, sy, tx, ty = out.boxes.unbind(-1)
        for value, bound in ((sx, 1.0), (sy, 0.2), (tx, 0.8), (ty, -0.8)):
            self.assert_close(value, torch.full_like(value, bound))
        theta = inverse_theta(out.boxes)
        layer = paste(torch.rand(2, 3, 1, 8, 8, dtype=dtype), out.boxes, (12, 16))
        loss = layer.sum() + out.depths.sum()
        grads = torch.autograd.grad(loss, [p for p in det.parameters()], allow_unused=True)
        assert _finite(theta, layer, *(g for g in grads if g is not None))

    @DTYPES
    def test_focal_bump_at_and_past_its_edge(self, dtype):
        x = torch.tensor(
            [0.0, 0.5, 0.95, 1 - 1e-7, 1.0, 1 + 1e-7, 2.0], dtype=dtype, requires_grad=True
        )
        for y in (torch.zeros_like(x), x * 0.3):
            G = focal_bump_at(x, y)
            (g,) = torch.autograd.grad(G.sum(), x)
            assert _finite(G, g)
            assert (G >= 0).all() and (G <= 1).all()
            assert torch.equal(G[4:], torch.zeros(3, dtype=dtype))
        self.assert_close(
            focal_bump_at(x[:3], torch.zeros(3, dtype=dtype)),
            torch.tensor([1.0, 0.7165, 1.0e-4], dtype=dtype),
            rtol=0,
            atol=1e-4,
        )


# ---------------------------------------------------------------------------- NNOPCS
def _flattened(species, axis: int):
    """``species`` with every primitive squashed to zero thickness along world ``axis``."""
    prims = []
    for p in species.primitives:
        axes = np.array(p.axes, dtype=np.float64)
        axes[axis] = 0.0  # the world-from-local map loses its ``axis`` row
        centre = list(p.centre)
        centre[axis] = 0.0
        prims.append(dataclasses.replace(p, centre=tuple(centre), axes=tuple(map(tuple, axes))))
    return dataclasses.replace(species, primitives=tuple(prims))


class TestNNOPCSExtremes(BaseTester):
    @pytest.mark.parametrize("axis", [0, 1, 2])
    def test_flat_body_normalises_finitely(self, axis):
        flat = _flattened(BIPED, axis)
        bounds = nnopcs_bounds(flat)
        assert math.isfinite(bounds.extent) and bounds.extent > 0
        assert bounds.hi[axis] == bounds.lo[axis] == 0.0
        g = torch.Generator().manual_seed(axis)
        n = 200
        part = torch.randint(0, len(flat.primitives), (n,), generator=g)
        local = torch.nn.functional.normalize(
            torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1
        ).requires_grad_(True)
        values = nnopcs_of(flat, part, local)
        (grad,) = torch.autograd.grad(values.sum(), local)
        assert _finite(values, grad)
        assert (values >= 0).all() and (values <= 1).all()
        # the flat axis sits in the middle of the cube; the others still spread out
        self.assert_close(values[:, axis], torch.full((n,), 0.5, dtype=torch.float64))
        others = [a for a in range(3) if a != axis]
        assert (values[:, others].amax(0) - values[:, others].amin(0)).max() > 0.5
        # round trip through the normalisation
        points = canonical_points(flat, part, local.detach())
        self.assert_close(bounds.denormalise(bounds.normalise(points)), points)

    def test_body_of_zero_size_is_rejected(self):
        """Fixed: a zero extent gave 0 / 0 = NaN, which the clamp to [0, 1] kept."""
        point = dataclasses.replace(
            BIPED,
            primitives=tuple(
                dataclasses.replace(p, centre=(0.0, 0.0, 0.0), radii=(0.0, 0.0, 0.0))
                for p in BIPED.primitives
            ),
        )
        with pytest.raises(ValueError, match="zero size along every axis"):
            nnopcs_bounds(point)


# ---------------------------------------------------------------------------- renderer
def _renderer_case(name: str, dtype):
    from tests.netepu.geometry.test_renderer import _kps, _tiny_model
    from tests.netepu_world import ring

    model = _tiny_model(dtype=dtype)
    cam_obj = ring(n=1)[0]
    cam = {k: v[None] for k, v in cam_obj.tensors(dtype).items()}
    kps = _kps(dtype=dtype)
    centre = torch.as_tensor(np.asarray(cam_obj.center), dtype=dtype)
    if name == "some_behind":  # three keypoints mirrored behind the camera
        kps[0, :3] = centre + 0.5 * (centre - kps[0, :3])
    elif name == "on_camera_plane":  # two keypoints at depth exactly 0
        kps[0, :2] = centre
    elif name == "coincident":
        kps = kps[:, :1].expand_as(kps).clone()
    elif name == "outside_image":  # 20 m to the camera's right
        kps = kps + 20 * cam["R"][0, 0]
    return model, cam_obj, cam, kps


class TestRendererExtremes(BaseTester):
    @DTYPES
    @pytest.mark.parametrize(
        "case", ["some_behind", "on_camera_plane", "coincident", "outside_image"]
    )
    def test_render_finite_with_gradients(self, case, dtype):
        model, _, cam, kps = _renderer_case(case, dtype)
        kps.requires_grad_(True)
        code = model.encode(kps)
        uv = torch.rand(1, 25, 2, dtype=dtype, generator=torch.Generator().manual_seed(0)) * 60
        out = model.renderer(kps, code.features, code.z, cam, uv)
        assert _finite(out["logit"], out["depth"], out["nnopcs"])
        loss = out["logit"].sum() + out["depth"].sum() + out["nnopcs"].sum()
        grads = torch.autograd.grad(loss, [kps, *model.parameters()], allow_unused=True)
        assert _finite(*(g for g in grads if g is not None))

    @pytest.mark.parametrize("mode", ["culled", "coarse_to_fine"])
    def test_all_keypoints_outside_the_image_render_background(self, mode):
        from netepu.geometry.maps import BACKGROUND_LOGIT, MapSettings, render_maps

        model, cam_obj, cam, kps = _renderer_case("outside_image", torch.float64)
        with torch.no_grad():
            ctx = model.prepare(model.encode(kps), cam, kps)
            maps = render_maps(model.query, ctx, cam_obj.size, MapSettings.defaults(mode=mode))
        assert maps.evaluated.tolist() == [0]
        assert torch.equal(maps.logit, torch.full_like(maps.logit, BACKGROUND_LOGIT))
        assert torch.equal(maps.depth, torch.zeros_like(maps.depth))
        assert _finite(maps.depth_norm, maps.nnopcs)

    @pytest.mark.parametrize("case", ["some_behind", "on_camera_plane", "coincident"])
    def test_maps_finite(self, case):
        from netepu.geometry.maps import MapSettings, render_maps

        model, cam_obj, cam, kps = _renderer_case(case, torch.float32)
        with torch.no_grad():
            ctx = model.prepare(model.encode(kps), cam, kps)
            for mode in ("dense", "culled", "coarse_to_fine"):
                maps = render_maps(model.query, ctx, cam_obj.size, MapSettings.defaults(mode=mode))
                assert _finite(maps.logit, maps.depth, maps.depth_norm, maps.nnopcs)

    def test_every_keypoint_behind_the_camera_is_a_clear_error(self):
        model, _, cam, kps = _renderer_case("some_behind", torch.float64)
        centre = kps[0, 0]  # the first keypoint was mirrored behind the camera
        behind = centre.expand_as(kps).clone()
        with pytest.raises(ValueError, match="behind their camera"):
            model.renderer(
                behind,
                torch.zeros(1, kps.shape[1], 16, dtype=torch.float64),
                torch.zeros(1, 32, dtype=torch.float64),
                cam,
                torch.zeros(1, 1, 2, dtype=torch.float64),
            )


class TestTextureVAEExtremes:
    """The texture VAE's KLD and reparameterisation at log-variances of +-50."""

    @given(
        mu=st.floats(-1e3, 1e3),
        logvar=st.floats(-50.0, 50.0),
    )
    @settings(max_examples=60, deadline=None)
    def test_kld_finite_and_equal_to_its_float64_closed_form(self, mu, logvar):
        from netepu.texture.losses import kld

        m = torch.tensor([[mu, -mu]], dtype=torch.float32, requires_grad=True)
        lv = torch.tensor([[logvar, -logvar]], dtype=torch.float32, requires_grad=True)
        k = kld(m, lv)
        k.backward()
        assert _finite(k, m.grad, lv.grad)
        closed = sum(
            0.5 * (x * x + math.exp(v) - 1.0 - v) for x, v in ((mu, logvar), (-mu, -logvar))
        )
        assert math.isclose(k.item(), closed, rel_tol=1e-5, abs_tol=1e-5)
        # d KLD / d logvar = (exp(logvar) - 1) / 2, of either sign; d KLD / d mu = mu
        assert math.isclose(
            lv.grad[0, 0].item(), 0.5 * math.expm1(logvar), rel_tol=1e-5, abs_tol=1e-6
        )
        assert math.isclose(m.grad[0, 0].item(), mu, rel_tol=1e-5, abs_tol=1e-6)

    def test_kld_limits(self):
        from netepu.texture.losses import kld

        # zero exactly at the prior; grows like exp(logvar) / 2 and like -logvar / 2 at the extremes
        assert kld(torch.zeros(1, 4), torch.zeros(1, 4)).item() == 0.0
        big = kld(
            torch.zeros(1, 1, dtype=torch.float64), torch.full((1, 1), 50.0, dtype=torch.float64)
        )
        small = kld(
            torch.zeros(1, 1, dtype=torch.float64), torch.full((1, 1), -50.0, dtype=torch.float64)
        )
        assert math.isclose(big.item(), 0.5 * (math.exp(50.0) - 51.0), rel_tol=1e-12)
        assert math.isclose(small.item(), 0.5 * (math.exp(-50.0) + 49.0), rel_tol=1e-12)

    @pytest.mark.parametrize("logvar", [-50.0, 50.0])
    def test_reparameterise_finite_with_gradients(self, logvar):
        from netepu.texture.losses import reparameterise

        mu = torch.zeros(3, 8, requires_grad=True)
        lv = torch.full((3, 8), logvar, requires_grad=True)
        noise = torch.randn(3, 8, generator=torch.Generator().manual_seed(0))
        z = reparameterise(mu, lv, noise)
        z.sum().backward()
        assert _finite(z, mu.grad, lv.grad)
        torch.testing.assert_close(z, noise * math.exp(logvar / 2))
