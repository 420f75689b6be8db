"""Renderer: projection through the calibration type, view-frame invariances, permutations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from netepu.geometry.model import build_geometry_model
from netepu.geometry.networks import KeypointEncoder, denormalise_keypoints, normalise_keypoints
from netepu.geometry.renderer import to_frame, view_frame
from tests.base import BaseTester
from tests.netepu_world import K_TOY, RADIUS, ring, toy_pose

TINY = {
    "encoder": {"width": 16, "latent": 32, "n_blocks": 1, "n_freq": 2},
    "decoder": {"features": 16, "bottleneck": 16, "n_blocks": 2, "k_first": 3},
    "renderer": {"width": 16, "n_blocks_2d": 2, "k_2d": 3, "k": 5, "n_freq": 2, "hidden": 8,
                 "groups": 4, "head_hidden": 16, "head_blocks": 1},
}


def _tiny_model(seed=0, dtype=torch.float64, **renderer):
    torch.manual_seed(seed)
    cfg = {**TINY, "renderer": {**TINY["renderer"], **renderer}}
    return build_geometry_model(cfg, K_TOY, RADIUS).to(dtype)


def _kps(seed=0, dtype=torch.float64):
    return torch.from_numpy(toy_pose(np.random.default_rng(seed))).to(dtype)[None]


class TestViewFrame(BaseTester):
    def test_projection_agrees_with_calibration(self, random_cameras):
        kps = _kps()
        for cam in random_cameras:  # includes 4-, 5- and 8-coefficient distortion
            uv_ref, z_ref = cam.project(kps[0].numpy())
            frame = view_frame(kps, {k: v[None] for k, v in cam.tensors(torch.float64).items()},
                               RADIUS)
            self.assert_close(frame.uv[0], torch.from_numpy(uv_ref))
            self.assert_close(frame.depth[0], torch.from_numpy(z_ref))

    def test_frame_known_values(self):
        cam = ring(n=1)[0]
        kps = _kps()
        frame = view_frame(kps, {k: v[None] for k, v in cam.tensors(torch.float64).items()},
                           RADIUS)
        Z = frame.depth[0]
        self.assert_close(frame.depth_ref[0], Z.mean())
        self.assert_close(frame.scale[0], cam.K[0, 0] * RADIUS / Z.mean())
        self.assert_close(frame.positions[0, :, 2], (Z - Z.mean()) / RADIUS)
        self.assert_close(frame.positions[0, :, :2].mean(0), torch.zeros(2, dtype=torch.float64))
        self.assert_close(to_frame(frame.uv, frame), frame.positions[..., :2])

    def test_behind_camera_raises(self):
        cam = ring(n=1)[0]
        p = {k: v[None] for k, v in cam.tensors(torch.float64).items()}
        behind = torch.from_numpy(cam.center + 3 * (cam.center - np.array([0, 0, 0.7])))
        with pytest.raises(ValueError, match="behind"):
            view_frame(behind.reshape(1, 1, 3).expand(1, 3, 3).clone(), p, RADIUS)


class TestRenderer(BaseTester):
    def test_resolution_independent(self):
        """The same camera at twice the resolution renders the same values at the same points."""
        model = _tiny_model()
        cam = ring(n=1, size=(64, 48))[0]
        big = cam.scaled((128, 96))
        kps = _kps()
        code = model.encode(kps)
        uv = torch.rand(1, 20, 2, dtype=torch.float64) * 40
        uv_big = (uv + 0.5) * 2 - 0.5  # cv2.resize's pixel-centre mapping
        out = model.query(model.prepare(code, {k: v[None] for k, v in
                                               cam.tensors(torch.float64).items()}, kps), uv)
        out_big = model.query(model.prepare(code, {k: v[None] for k, v in
                                                   big.tensors(torch.float64).items()}, kps),
                              uv_big)
        for key in ("logit", "depth", "nnopcs"):
            self.assert_close(out_big[key], out[key])

    @pytest.mark.parametrize("k", [3, 0])
    def test_invariant_to_keypoint_order(self, k):
        """Permuting keypoints and their features together leaves every render unchanged."""
        model = _tiny_model(k=k)
        cam = {kk: v[None] for kk, v in ring(n=1)[0].tensors(torch.float64).items()}
        kps = _kps(1)
        code = model.encode(kps)
        uv = torch.rand(1, 30, 2, dtype=torch.float64) * torch.tensor([64.0, 48.0])
        ref = model.renderer(kps, code.features, code.z, cam, uv)
        perm = torch.randperm(K_TOY)
        out = model.renderer(kps[:, perm], code.features[:, perm], code.z, cam, uv)
        for key in ("logit", "depth", "nnopcs"):
            self.assert_close(out[key], ref[key])

    def test_encoder_invariant_to_order_with_identities(self):
        torch.manual_seed(0)
        enc = KeypointEncoder(K_TOY, width=16, latent=32, n_blocks=2, n_freq=2).double()
        x = torch.randn(2, K_TOY, 3, dtype=torch.float64)
        perm = torch.randperm(K_TOY)
        ident = torch.eye(K_TOY, dtype=torch.float64).expand(2, -1, -1)
        self.assert_close(enc(x[:, perm], ident[:, perm]), enc(x))
        # ... but not to reordering the keypoints alone: identity is what tells them apart
        assert not torch.allclose(enc(x[:, perm]), enc(x))

    def test_depth_is_metric(self):
        model = _tiny_model()
        cam = {kk: v[None] for kk, v in ring(n=1)[0].tensors(torch.float64).items()}
        kps = _kps()
        ctx = model.prepare(model.encode(kps), cam, kps)
        out = model.query(ctx, torch.rand(1, 5, 2, dtype=torch.float64) * 40)
        self.assert_close(out["depth"], ctx.frame.depth_ref[:, None] + RADIUS * out["depth_norm"])

    @pytest.mark.parametrize("shared", [True, False])
    def test_selected_outputs_match_the_full_query(self, shared):
        """A query of some outputs gives exactly those of the full query; with separate heads
        the other heads do not run (their parameters get no gradient)."""
        model = _tiny_model(shared_head=shared)
        for head in model.renderer.heads:  # the last layers start at non-zero values
            torch.nn.init.normal_(head.out.weight)
        cam = {kk: v[None] for kk, v in ring(n=1)[0].tensors(torch.float64).items()}
        kps = _kps()
        ctx = model.prepare(model.encode(kps), cam, kps)
        uv = torch.rand(1, 7, 2, dtype=torch.float64) * 40
        full = model.query(ctx, uv)
        assert set(full) == {"logit", "depth", "depth_norm", "nnopcs"}
        cases = ((("logit",), {"logit"}), (("nnopcs",), {"nnopcs"}),
                 (("depth", "nnopcs"), {"depth", "depth_norm", "nnopcs"}))
        for outputs, keys in cases:
            part = model.query(ctx, uv, outputs)
            assert set(part) == keys
            for k in keys:
                self.assert_close(part[k], full[k])
        model.zero_grad()
        model.query(ctx, uv, ("logit",))["logit"].sum().backward(retain_graph=True)
        grads = [h.out.weight.grad is not None for h in model.renderer.heads]
        assert grads == ([True] if shared else [True, False, False])
        with pytest.raises(ValueError, match="outputs"):
            model.query(ctx, uv, ("colour",))
        with pytest.raises(ValueError, match="outputs"):
            model.query(ctx, uv, ())

    def test_reference_mode_same_function(self):
        model = _tiny_model()
        cam = {kk: v[None] for kk, v in ring(n=1)[0].tensors(torch.float64).items()}
        kps = _kps()
        code = model.encode(kps)
        uv = torch.rand(1, 25, 2, dtype=torch.float64) * 50
        fast = model.query(model.prepare(code, cam, kps), uv)
        model.renderer.vca.mode = "reference"
        ref = model.query(model.prepare(code, cam, kps), uv)
        self.assert_close(fast["logit"], ref["logit"])

    def test_gradcheck_render_path(self):
        """Float64 gradients of a render w.r.t. keypoints and features (inverse rendering)."""
        model = _tiny_model()
        cam = {kk: v[None] for kk, v in ring(n=1)[0].tensors(torch.float64).items()}
        code = model.encode(_kps())
        uv = torch.tensor([[[30.0, 20.0], [33.0, 25.0]]], dtype=torch.float64)

        def fn(kps, feats, z):
            return model.renderer(kps, feats, z, cam, uv)["logit"]

        assert self.gradcheck(fn, [_kps(), code.features.detach(), code.z.detach()])

    def test_keypoint_normalisation_roundtrip(self):
        kps = _kps()
        n, c = normalise_keypoints(kps, RADIUS)
        self.assert_close(n.mean(1), torch.zeros(1, 3, dtype=torch.float64))
        self.assert_close(denormalise_keypoints(n, c, RADIUS), kps)
