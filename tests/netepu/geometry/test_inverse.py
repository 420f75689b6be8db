"""Inverse rendering: triangulation, rotations, recovering a known pose from own renders."""

from __future__ import annotations

import math

import numpy as np
import torch

from netepu.geometry.inverse import (
    InverseSettings,
    invert_silhouettes,
    rotate_about_up,
    triangulate_centroids,
)
from netepu.geometry.maps import MapSettings, render_maps
from nsd.evaluation.maps import silhouette_iou
from nsd.evaluation.pose import mpjpe
from tests.base import BaseTester
from tests.netepu_world import toy_pose, trained_toy


class TestHelpers(BaseTester):
    def test_rotate_about_up(self):
        up = torch.tensor([0.0, 0.0, 1.0])
        out = rotate_about_up(torch.tensor([[1.0, 0.0, 2.0]]), math.pi / 2, up)
        self.assert_close(out, torch.tensor([[0.0, 1.0, 2.0]]), atol=1e-6, rtol=0)

    def test_triangulate_known_point(self, random_cameras):
        """Masks centred on a point's projections (lens distortion included) give the point."""
        point = np.array([0.3, -0.2, 0.9])
        masks, cams = [], []
        for cam in random_cameras[:4]:
            uv, _ = cam.project(point[None])
            x, y = np.round(uv[0]).astype(int)
            m = np.zeros((cam.size[1], cam.size[0]), bool)
            m[y - 1:y + 2, x - 1:x + 2] = True
            masks.append(m)
            cams.append(cam.tensors(torch.float64))
        camera = {k: torch.stack([c[k] for c in cams]) for k in ("K", "R", "t")}
        camera["dist"] = torch.stack([torch.nn.functional.pad(c["dist"], (0, 8 - len(c["dist"])))
                                      for c in cams])
        est = triangulate_centroids(torch.from_numpy(np.stack(masks)), camera)
        assert np.linalg.norm(est.numpy() - point) < 0.03  # pixel rounding at ~300 px focal


def test_recovers_known_pose_from_own_renders():
    """Silhouettes rendered by the model at a known pose lead back to that pose."""
    model, data, _ = trained_toy()
    views = data.evaluation["train"]
    truth = views.keypoints[0]
    sel = [0, 2, 4]
    cam = views.camera[sel]
    with torch.no_grad():
        code = model.encode(truth[None])
        own = render_maps(model.query, model.prepare(code, cam), views.size,
                          MapSettings.defaults()).silhouette
    template = torch.from_numpy(toy_pose(np.random.default_rng(7))).float()[None]
    start_error = mpjpe(template[0] - template[0].mean(0) + truth.mean(0), truth)
    res = invert_silhouettes(model, own, cam, template,
                             InverseSettings(steps=80, points_per_view=256, headings=4))
    error = mpjpe(res.keypoints, code.keypoints[0])
    assert error < 0.05 and error < 0.3 * start_error, (error, start_error)
    with torch.no_grad():
        again = render_maps(model.query, model.prepare(model.decode(res.z[None],
                                                                    res.centre[None]), cam),
                            views.size, MapSettings.defaults()).silhouette
    assert silhouette_iou(again, own).min() > 0.85
    assert all(p.requires_grad for p in model.parameters())  # model left as found


class _ScaledEncoder(torch.nn.Module):
    """An encoder whose codes are multiplied by ``a``."""

    def __init__(self, inner: torch.nn.Module, a: float) -> None:
        super().__init__()
        self.inner, self.a, self.n_keypoints = inner, a, inner.n_keypoints

    def forward(self, keypoints):
        return self.inner(keypoints) * self.a


class _ScaledDecoder(torch.nn.Module):
    """The matching decoder: divides its codes by ``a`` first (same model, codes x a)."""

    def __init__(self, inner: torch.nn.Module, a: float) -> None:
        super().__init__()
        self.inner, self.a = inner, a

    def forward(self, z, z_features=None):
        return self.inner(z / self.a, None if z_features is None else z_features / self.a)


def test_recovery_does_not_depend_on_the_scale_of_codes():
    """Trained codes are small (entries ~1e-2); the same model with codes x 0.01 is inverted
    as well as the original (steps are taken in the codes' own scale)."""
    model, data, _ = trained_toy()
    views = data.evaluation["train"]
    truth, sel = views.keypoints[0], [0, 2, 4]
    cam = views.camera[sel]
    with torch.no_grad():
        own = render_maps(model.query, model.prepare(model.encode(truth[None]), cam),
                          views.size, MapSettings.defaults()).silhouette
    template = torch.from_numpy(toy_pose(np.random.default_rng(7))).float()[None]
    settings = InverseSettings(steps=80, points_per_view=256, headings=4, latent_weight=0.0)
    plain = invert_silhouettes(model, own, cam, template, settings)
    encoder, decoder = model.encoder, model.decoder
    try:
        model.encoder = _ScaledEncoder(encoder, 0.01)
        model.decoder = _ScaledDecoder(decoder, 0.01)
        small = invert_silhouettes(model, own, cam, template, settings)
    finally:
        model.encoder, model.decoder = encoder, decoder
    assert small.z.abs().max() < 0.1 * plain.z.abs().max()  # the codes really are smaller
    assert mpjpe(small.keypoints, plain.keypoints) < 0.02
