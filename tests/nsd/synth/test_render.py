"""render_views: geometric invariants of the ground-truth maps, NNOPCS, textures, visibility."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pycocotools import mask as mask_utils

from nsd.core.errors import ConfigError
from nsd.ops.boxes import mask_boxes_xyxy
from nsd.synth.body import Pose, make_individual
from nsd.synth.coco import encode_masks
from nsd.synth.motion import sample_pose
from nsd.synth.nnopcs import nnopcs_bounds, nnopcs_of
from nsd.synth.raycast import Ellipsoids, cast_rays
from nsd.synth.render import render_views
from nsd.synth.rigs import look_at, ring_rig
from tests.base import assert_close


@pytest.fixture(scope="module")
def pair():
    """Two individuals close together and one render of them from a ring of 4 cameras."""
    rng = np.random.default_rng(11)
    inds = [make_individual("quadruped", 0, seed=2), make_individual("biped", 1, seed=2)]
    poses = [
        sample_pose(inds[0], rng, position=(-0.3, -0.5)),
        sample_pose(inds[1], rng, position=(0.4, 0.6)),
    ]
    rig = ring_rig(4, radius=4.0, height=1.8, size=(64, 48), fov_deg=55, start_deg=20)
    return inds, poses, rig, render_views(inds, poses, rig)


def _surface_point(ind, pose, part: int, u: torch.Tensor) -> torch.Tensor:
    body = ind.posed(pose.to(torch.float64))
    return body.centres[part] + body.axes[part] @ (body.radii[part] * u)


class TestMasksAndDepth:
    def test_shapes_and_dtypes(self, pair):
        inds, _, rig, out = pair
        V, N, H, W = len(rig), len(inds), 48, 64
        assert out["rgb"].shape == (V, H, W, 3) and out["rgb"].dtype == torch.float32
        assert out["amodal"].shape == (V, N, H, W) and out["amodal"].dtype == torch.bool
        assert out["instance"].shape == (V, H, W) and out["boxes"].shape == (V, N, 4)
        assert [k.shape for k in out["keypoints2d"]] == [(V, 25, 2), (V, 17, 2)]

    def test_visible_inside_amodal(self, pair):
        _, _, _, out = pair
        assert not (out["visible"] & ~out["amodal"]).any()
        assert out["visible"].any() and (out["amodal"] & ~out["visible"]).any()  # occlusion happens

    def test_union_of_visible_masks_is_the_foreground(self, pair):
        _, _, _, out = pair
        union = out["visible"].any(1)
        assert torch.equal(union, out["instance"] >= 0)
        assert torch.equal(union, torch.isfinite(out["depth"]))
        assert torch.equal(union, out["amodal"].any(1))
        # outside the union the image is the static backdrop, inside it is not
        assert torch.equal(out["rgb"][~union], out["background"][~union])
        differs = (out["rgb"][union] - out["background"][union]).abs().amax(-1) > 1e-3
        assert differs.float().mean() > 0.95

    def test_depth_is_the_minimum_of_amodal_depths(self, pair):
        _, _, _, out = pair
        assert_close(out["depth"], out["amodal_depth"].amin(1))
        visible_depth = torch.where(out["visible"], out["amodal_depth"], torch.inf).amin(1)
        assert_close(out["depth"], visible_depth)

    def test_boxes_match_pycocotools(self, pair):
        _, _, _, out = pair
        for v in range(out["visible"].shape[0]):
            for key, masks in (("boxes", out["visible"][v]), ("amodal_boxes", out["amodal"][v])):
                ref = mask_utils.toBbox(encode_masks(masks.numpy()))
                x0, y0, x1, y1 = out[key][v].numpy().T
                np.testing.assert_array_equal(np.stack([x0, y0, x1 - x0, y1 - y0], 1), ref)

    def test_empty_mask_box_is_zero(self):
        m = torch.zeros(2, 5, 7, dtype=torch.bool)
        m[1, 2:4, 3] = True
        assert mask_boxes_xyxy(m).tolist() == [[0, 0, 0, 0], [3, 2, 4, 4]]

    def test_supersampling_changes_rgb_only_and_mostly_at_edges(self, pair):
        inds, poses, rig, out = pair
        ss = render_views(inds, poses, rig, supersample=3)
        for key in ("instance", "depth", "nnopcs", "amodal", "boxes"):
            assert torch.equal(ss[key], out[key]), key
        inst = out["instance"]
        edge = torch.zeros_like(inst, dtype=torch.bool)
        edge[:, 1:] |= inst[:, 1:] != inst[:, :-1]
        edge[:, :-1] |= inst[:, 1:] != inst[:, :-1]
        edge[:, :, 1:] |= inst[:, :, 1:] != inst[:, :, :-1]
        edge[:, :, :-1] |= inst[:, :, 1:] != inst[:, :, :-1]
        diff = (ss["rgb"] - out["rgb"]).abs().amax(-1)
        assert diff[edge].mean() > 3 * diff[~edge].mean()

    def test_no_background(self, pair):
        inds, poses, rig, _ = pair
        out = render_views(inds, poses, rig, background=False)
        bg = out["instance"] < 0
        assert (out["rgb"][bg] == 0).all() and (out["background"] == 0).all()

    def test_pose_count_mismatch(self, pair):
        inds, poses, rig, _ = pair
        with pytest.raises(ConfigError, match="poses"):
            render_views(inds, poses[:1], rig)

    def test_no_individuals_renders_the_backdrop(self, pair):
        _, _, rig, out = pair
        empty = render_views([], [], rig)
        assert (empty["instance"] < 0).all() and torch.isinf(empty["depth"]).all()
        assert_close(empty["rgb"], out["background"])


class TestNNOPCS:
    def test_range_and_background(self, pair):
        _, _, _, out = pair
        nn, fg = out["nnopcs"], out["instance"] >= 0
        assert nn.min() >= 0 and nn.max() <= 1
        assert (nn[~fg] == 0).all()
        assert nn[fg].std(0).min() > 0.05  # a real coordinate map, not a constant

    def test_bounds_hold_every_individual(self):
        # proportions vary, but every surface point maps into the cube (before the clamp)
        for name in ("biped", "quadruped"):
            b = nnopcs_bounds(make_individual(name).species)
            assert b.extent > 0 and np.all(np.array(b.lo) >= np.array(b.centre) - b.extent / 2)
            assert np.all(np.array(b.hi) <= np.array(b.centre) + b.extent / 2)

    def test_fixed_body_point_is_the_same_across_poses_and_cameras(self):
        """The NNOPCS of a body point is the same in every pose and every camera that sees it."""
        ind = make_individual("biped", 0, seed=4)
        rng = np.random.default_rng(5)
        poses = [sample_pose(ind, rng, variation=0.5) for _ in range(3)]
        rig = ring_rig(6, radius=3.0, height=1.4, size=(96, 96), fov_deg=45)
        parts = [ind.species.primitive_index(n) for n in ("chest", "skull", "left_thigh", "pelvis")]
        # upper chest front, side of the face, front of the thigh, back of the pelvis
        u = torch.tensor([[0.9, 0.0, 0.44], [0.6, 0.3, 0.74], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.2]])
        u = torch.nn.functional.normalize(u.double(), dim=-1)
        expected = nnopcs_of(ind.species, torch.tensor(parts), u)
        seen = np.zeros(len(parts), int)
        pixel_checks = 0
        for pose in poses:
            out = render_views([ind], [pose], rig, background=False)
            body = ind.posed(pose.to(torch.float64))
            E = Ellipsoids.concat([(body.centres, body.axes, body.radii)], torch.float64)
            for v, cam in enumerate(rig):
                o = torch.as_tensor(cam.center)[None]
                for i, (p, ui) in enumerate(zip(parts, u, strict=True)):
                    X = _surface_point(ind, pose, p, ui)
                    d = (X - o[0]) / (X - o[0]).norm()
                    hit = cast_rays(o, torch.zeros(1, dtype=torch.long), d[None], E)
                    if abs(hit.distance[0] - (X - o[0]).norm()) > 1e-6:
                        continue  # hidden from this camera
                    seen[i] += 1
                    # the exact ray through the point gives exactly its NNOPCS ...
                    got = nnopcs_of(ind.species, hit.part, hit.local)
                    assert_close(got[0], expected[i], atol=1e-6, rtol=0)
                    # ... and the rendered map at its pixel agrees up to the pixel footprint
                    (uv,), _ = cam.project(X[None].numpy())
                    px, py = (round(float(c)) for c in uv)
                    if out["instance"][v, py, px] == 0 and out["part"][v, py, px] == p:
                        pixel_checks += 1
                        err = (out["nnopcs"][v, py, px].double() - expected[i]).abs().max()
                        assert err < 0.03
        assert (seen >= 3).all() and pixel_checks >= 6, (seen, pixel_checks)

    def test_nnopcs_independent_of_proportions(self):
        """The same anatomical point of two differently built individuals has one NNOPCS value."""
        a = make_individual("quadruped", 0, seed=1)
        b = make_individual("quadruped", 1, seed=9)
        assert not torch.allclose(a.radii, b.radii)
        rig = ring_rig(3, radius=4.5, height=1.5, size=(48, 48))
        for ind in (a, b):
            out = render_views([ind], [ind.rest_pose()], rig, background=False)
            fg = out["instance"] >= 0
            part = out["part"][fg]
            # every visible pixel's NNOPCS lies on the mean body's surface of its primitive
            mean_c = torch.tensor([p.centre for p in ind.species.primitives])
            mean_q = torch.tensor([p.axes for p in ind.species.primitives])
            mean_a = torch.tensor([p.radii for p in ind.species.primitives])
            P = nnopcs_bounds(ind.species).denormalise(out["nnopcs"][fg].double()).float()
            local = ((P - mean_c[part]).unsqueeze(-2) @ mean_q[part]).squeeze(-2) / mean_a[part]
            assert_close(local.norm(dim=-1), torch.ones(len(local)), atol=1e-4, rtol=0)


class TestTexture:
    def test_texture_sticks_to_the_body(self):
        """Albedo is a function of NNOPCS only: equal NNOPCS, equal albedo, in any pose."""
        ind = make_individual("quadruped", 0, texture_id=0, seed=3)
        rng = np.random.default_rng(0)
        rig = ring_rig(3, radius=4.5, height=1.6, size=(48, 48))
        for pose in (ind.rest_pose(), sample_pose(ind, rng), sample_pose(ind, rng)):
            out = render_views([ind], [pose], rig)
            fg = out["instance"] >= 0
            assert_close(out["albedo"][fg], ind.texture(out["nnopcs"][fg]), atol=1e-6, rtol=0)
        # a fixed body point keeps its albedo in two poses
        part = torch.tensor([ind.species.primitive_index("barrel")])
        u = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
        nn = nnopcs_of(ind.species, part, u)
        assert_close(ind.texture(nn), ind.texture(nn.clone()))

    def test_lambertian_shading(self, pair):
        _, _, _, out = pair
        fg = out["instance"] >= 0
        light = torch.nn.functional.normalize(torch.tensor([0.4, 0.25, 1.0]), dim=0)
        cos = (out["normal"][fg] * light).sum(-1).clamp_min(0)
        expected = out["albedo"][fg] * (0.35 + 0.65 * cos)[:, None]
        assert_close(out["rgb"][fg], expected, atol=1e-6, rtol=0)


class TestKeypoints:
    def test_projection_and_in_image_flag(self, pair):
        inds, poses, rig, out = pair
        for n, (ind, pose) in enumerate(zip(inds, poses, strict=True)):
            X = ind.keypoints3d(pose.to(torch.float64))
            assert_close(out["keypoints3d"][n], X)
            for v, cam in enumerate(rig):
                uv, z = cam.project(X.numpy())
                np.testing.assert_allclose(out["keypoints2d"][n][v].numpy(), uv, atol=1e-9)
                inside = (
                    (uv[:, 0] >= -0.5) & (uv[:, 0] < 63.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < 47.5)
                )
                np.testing.assert_array_equal(
                    out["keypoint_visibility"][n][v].numpy() > 0, inside & (z > 0)
                )

    def test_point_hidden_in_one_camera_visible_in_another(self):
        """A constructed configuration: B stands between camera 'front' and A's chest."""
        a = make_individual("biped", 0, seed=0, proportion_variation=0.0)
        b = make_individual("biped", 1, seed=0, proportion_variation=0.0)
        zeros = torch.zeros(17, 3, dtype=torch.float64)
        # A at the origin facing +y; B 1.2 m along +x, facing +x
        pa = a.place_on_ground(
            Pose(torch.zeros(3).double(), torch.tensor(np.pi / 2).double(), zeros)
        )
        pb = b.place_on_ground(
            Pose(torch.tensor([1.2, 0.0, 0.0]).double(), torch.tensor(0.0).double(), zeros)
        )
        thorax = a.species.index("thorax")
        XA = a.keypoints3d(pa)[thorax]
        front = look_at("front", (6.0, 0.0, float(XA[2])), XA.tolist(), (64, 64), fov_deg=40)
        side = look_at("side", (0.0, 6.0, float(XA[2])), XA.tolist(), (64, 64), fov_deg=40)
        out = render_views([a, b], [pa, pb], [front, side])
        vis_a = out["keypoint_visibility"][0][:, thorax]
        assert vis_a.tolist() == [1, 2]  # occluded by B in 'front', visible in 'side'
        assert (
            out["keypoint_visibility"][1][0, b.species.index("thorax")] == 2
        )  # B's own is visible
        # the surface point of A's chest that 'side' sees through the keypoint ray
        body = a.posed(pa)
        E = Ellipsoids.concat([(body.centres, body.axes, body.radii)], torch.float64)
        o = torch.as_tensor(side.center)[None]
        d = (XA - o[0]) / (XA - o[0]).norm()
        hit = cast_rays(o, torch.zeros(1, dtype=torch.long), d[None], E)
        S = o[0] + hit.distance[0] * d
        for v, cam, who in ((0, front, 1), (1, side, 0)):
            (uv,), (z,) = cam.project(S[None].numpy())
            px, py = (round(float(c)) for c in uv)
            assert out["instance"][v, py, px] == who
            assert out["amodal"][v, 0, py, px]  # A covers the pixel either way
            if who == 0:
                assert abs(out["depth"][v, py, px] - z) < 0.03  # visible: depth is the point's
            else:
                assert out["depth"][v, py, px] < z - 0.3  # hidden: something much nearer
