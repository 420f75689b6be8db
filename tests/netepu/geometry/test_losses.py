"""Loss terms and metrics: known values."""

from __future__ import annotations

import math

import torch

from netepu.geometry.losses import (
    GeometryLossWeights,
    depth_loss,
    geometry_loss,
    keypoint_loss,
    latent_loss,
    nnopcs_loss,
    silhouette_loss,
)
from nsd.evaluation.maps import depth_mae, nnopcs_mse, silhouette_iou
from nsd.evaluation.pose import mpjpe
from tests.base import BaseTester


class TestLosses(BaseTester):
    def test_known_values(self):
        self.assert_close(silhouette_loss(torch.zeros(2, 3), torch.ones(2, 3)),
                          torch.tensor(math.log(2)))
        a = torch.zeros(1, 2, 3)
        b = torch.tensor([[[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]]])
        self.assert_close(keypoint_loss(a, b), torch.tensor(3.0))  # (5 + 1) / 2
        # 2-norm over a view's points, mean over views: (5 + 0) / 2
        self.assert_close(depth_loss(torch.tensor([[3.0, 4.0], [1.0, 1.0]]),
                                     torch.tensor([[0.0, 0.0], [1.0, 1.0]])), torch.tensor(2.5))
        self.assert_close(nnopcs_loss(torch.full((1, 2, 3), 0.5), torch.zeros(1, 2, 3)),
                          torch.tensor(0.25))
        self.assert_close(latent_loss(torch.tensor([[3.0, 4.0], [0.0, 0.0]])), torch.tensor(2.5))

    def test_shipped_weights(self):
        """NePu's keypoint, depth and latent weights; silhouette 10 and NNOPCS 100 instead of
        NePu's 3 and 1 (docs/benchmarks/netepu_geometry_recipe.md)."""
        w = GeometryLossWeights.defaults()
        assert (w.silhouette, w.keypoints, w.depth, w.nnopcs, w.latent) == (10, 2, 1, 100, 1 / 16)
        terms = {k: torch.tensor(v) for k, v in (("silhouette", 1.0), ("keypoints", 2.0),
                                                  ("depth", 3.0), ("nnopcs", 4.0),
                                                  ("latent", 16.0))}
        self.assert_close(geometry_loss(terms, w)["loss"], torch.tensor(10 + 4 + 3 + 400 + 1.0))


class TestMetrics(BaseTester):
    def test_iou(self):
        a = torch.zeros(2, 4, 4, dtype=torch.bool)
        b = torch.zeros(2, 4, 4, dtype=torch.bool)
        a[0, :2] = True
        b[0, 1:3] = True
        iou = silhouette_iou(a, b)
        self.assert_close(iou, torch.tensor([4 / 12, 1.0], dtype=torch.float64))

    def test_map_errors(self):
        pred = torch.zeros(1, 2, 2, 3)
        gt = torch.full((1, 2, 2, 3), 0.1)
        valid = torch.tensor([[[True, False], [False, False]]])
        self.assert_close(nnopcs_mse(pred, gt, valid), torch.tensor(0.01, dtype=torch.float64))
        self.assert_close(depth_mae(torch.ones(1, 2, 2), torch.zeros(1, 2, 2), valid),
                          torch.tensor(1.0, dtype=torch.float64))
        self.assert_close(mpjpe(torch.zeros(2, 3), torch.tensor([[0, 3.0, 4], [1.0, 0, 0]])),
                          torch.tensor(3.0, dtype=torch.float64))
