"""Pose regressor P (NSD stage 3): frozen 3D latent cloud -> 3D keypoints.

Two fully connected layers with dropout 0.5 (as in NSD / Rhodin et al. 2018),
trained with MSE on root-relative 3D keypoints in the camera frame from a
chosen fraction of labelled frames.
"""

from __future__ import annotations

from torch import Tensor, nn

__all__ = ["PoseRegressor"]


class PoseRegressor(nn.Module):
    """latent (B, P, 3) -> keypoints (B, K, 3).

    Args:
        points: latent cloud size P.
        keypoints: K.
        hidden: width of both hidden layers (NSD: 1024 or 2048).
        dropout: NSD: 0.5.
    """

    def __init__(self, points: int = 200, keypoints: int = 17, hidden: int = 1024,
                 dropout: float = 0.5) -> None:
        super().__init__()
        self.keypoints = keypoints
        self.net = nn.Sequential(
            nn.Flatten(), nn.Linear(points * 3, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
            nn.Linear(hidden, hidden), nn.ReLU(inplace=True), nn.Dropout(dropout),
            nn.Linear(hidden, keypoints * 3),
        )

    def forward(self, latent: Tensor) -> Tensor:
        return self.net(latent).view(-1, self.keypoints, 3)
