r"""The 2D neural renderer: keypoints + local features -> silhouette logit, depth, NNOPCS per pixel.

NePu's renderer (NeTePu sec. 3.1, eq. 1), evaluated at arbitrary query pixels.

View frame (:func:`view_frame`)
    Keypoints are projected with the camera (:func:`nsd.cameras.projection.project_points`,
    lens distortion included). Pixels and keypoints are then expressed in a
    frame that does not depend on image size, focal length or distance: with
    :math:`\bar Z` the mean camera depth of the keypoints, :math:`\bar u` the
    mean projected keypoint and :math:`s = \sqrt{f_x f_y}\, r / \bar Z` the size
    of one body radius ``r`` in pixels,

    .. math::
        \tilde u = (u - \bar u) / s,\qquad d_j = (Z_j - \bar Z) / r .

    ``d_j`` is NePu's per-keypoint normalised depth (NePu min-max normalises
    per view, which degenerates when the body is seen end-on; dividing by the
    body radius keeps one metric scale in every view). Predicted depth maps are
    :math:`Z = \bar Z + r\,\hat d`.

Rendering
    2D point-transformer blocks run over the keypoints at :math:`(\tilde u_j, d_j)`;
    each query pixel runs a vector cross-attention
    (:class:`netepu.geometry.attention.VectorCrossAttention`) over its ``k`` nearest
    projected keypoints (offsets :math:`(\tilde u - \tilde u_j, d_j)`) plus a
    global token from ``z``; heads (NePu's residual FC blocks) give the
    silhouette logit, normalised depth :math:`\hat d` and the 3 NNOPCS channels.
    Everything that does not depend on the pixel is computed once per view by
    :meth:`NeuralRenderer2D.prepare`.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from netepu.geometry.attention import PointTransformerBlock, VectorCrossAttention
from nsd.cameras.batch import CameraBatch
from nsd.cameras.projection import project_points

__all__ = [
    "OUTPUTS",
    "NeuralRenderer2D",
    "RenderContext",
    "RenderHead",
    "ViewFrame",
    "check_in_front",
    "to_frame",
    "view_frame",
]

OUTPUTS = ("logit", "depth", "nnopcs")  # what a query renders; separate heads in this order
MIN_DEPTH = 1e-3  # keypoints closer to the camera than this (scene units) are rejected


@dataclass
class ViewFrame:
    """The renderer's normalised 2D frame of one view per batch item.

    Attributes:
        uv: projected keypoints, pixels, (B, K, 2).
        depth: camera depth Z of the keypoints, (B, K).
        origin: mean projected keypoint :math:`\\bar u`, pixels, (B, 2).
        scale: pixels per body radius :math:`s`, (B,).
        depth_ref: mean keypoint depth :math:`\\bar Z`, (B,).
        radius: body radius r (scene units).
        positions: keypoints in the frame :math:`(\\tilde u_j, d_j)`, (B, K, 3).
    """

    uv: Tensor
    depth: Tensor
    origin: Tensor
    scale: Tensor
    depth_ref: Tensor
    radius: float
    positions: Tensor


def check_in_front(depth_ref: Tensor) -> None:
    """Raise ValueError naming the batch items whose keypoints' mean depth (B,) is not in
    front of their camera (a data-dependent check: it waits for a GPU)."""
    if not torch.all(depth_ref > MIN_DEPTH):
        bad = torch.nonzero(depth_ref <= MIN_DEPTH).flatten().tolist()
        raise ValueError(f"keypoints of batch items {bad} lie behind their camera")


def view_frame(keypoints: Tensor, camera: CameraBatch, radius: float) -> ViewFrame:
    """Project keypoints and build the view frame (see the module docstring).

    Args:
        keypoints: world keypoints, (B, K, 3).
        camera: a :class:`nsd.cameras.batch.CameraBatch` of B cameras (or a mapping with
            ``K``, ``R``, ``t`` and optionally ``dist``).
        radius: body radius r.

    Returns:
        The :class:`ViewFrame`.

    Raises:
        ValueError: when the keypoints' mean lies behind the camera.
    """
    camera = CameraBatch.from_mapping(camera)
    uv, Z = project_points(keypoints, camera.K, camera.R, camera.t, camera.dist)
    depth_ref = Z.mean(dim=1)
    check_in_front(depth_ref)
    K = camera.K
    focal = torch.sqrt(K[..., 0, 0] * K[..., 1, 1])
    scale = focal * radius / depth_ref
    origin = uv.mean(dim=1)
    positions = torch.cat(
        [(uv - origin.unsqueeze(1)) / scale[:, None, None], ((Z - depth_ref[:, None]) / radius)
         .unsqueeze(-1)], dim=-1)
    return ViewFrame(uv, Z, origin, scale, depth_ref, radius, positions)


def to_frame(uv: Tensor, frame: ViewFrame) -> Tensor:
    """Pixels (B, Q, 2) -> frame coordinates :math:`\\tilde u`, (B, Q, 2)."""
    return (uv - frame.origin.unsqueeze(1)) / frame.scale[:, None, None]


class _ResnetBlockFC(nn.Module):
    """x + fc1(relu(fc0(relu(x)))), fc1 zero-initialised (NePu / occupancy networks)."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.fc0, self.fc1 = nn.Linear(width, width), nn.Linear(width, width)
        nn.init.zeros_(self.fc1.weight)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.fc1(torch.relu(self.fc0(torch.relu(x))))


class RenderHead(nn.Module):
    """NePu's render head: Linear, then blocks of (add Linear(y), residual FC block), Linear.

    Args:
        channels: C of the VCA output y.
        hidden: width of the head.
        n_blocks: residual blocks (NePu: 5).
        out: output channels.

    Shape:
        (..., C) -> (..., out).
    """

    def __init__(self, channels: int, hidden: int, n_blocks: int, out: int) -> None:
        super().__init__()
        self.init = nn.Linear(channels, hidden)
        self.cond = nn.ModuleList(nn.Linear(channels, hidden) for _ in range(n_blocks))
        self.blocks = nn.ModuleList(_ResnetBlockFC(hidden) for _ in range(n_blocks))
        self.out = nn.Linear(hidden, out)

    def forward(self, y: Tensor) -> Tensor:
        net = self.init(y)
        for cond, block in zip(self.cond, self.blocks, strict=True):
            net = block(net + cond(y))
        return self.out(torch.relu(net))


@dataclass
class RenderContext:
    """Per-view precomputation of :meth:`NeuralRenderer2D.prepare` (shared by all pixels).

    Attributes:
        frame: the view frame.
        prepared: the VCA's per-keypoint and per-image terms.
    """

    frame: ViewFrame
    prepared: dict[str, Tensor]


class NeuralRenderer2D(nn.Module):
    """Keypoint-driven 2D renderer of silhouette logit, depth and NNOPCS.

    Args:
        features: d_f of the keypoint features.
        latent: d_z of the global code.
        radius: body radius r (scene units) of the view frame.
        width: C of the 2D blocks and the VCA (NePu: 256).
        n_blocks_2d: 2D point-transformer blocks over the keypoints (NePu: 3).
        k_2d: neighbours of the first 2D block (NePu: 8; the others attend to all).
        k: neighbours of the VCA (NePu: 12; 20 for cows).
        n_freq: Fourier bands (NePu: 5).
        hidden: H of the VCA's attention MLP (NePu: C).
        groups: G of the VCA (NePu: C).
        vca_mode: ``"factorised"`` or ``"reference"`` (same function, NePu's cost).
        head_hidden: width of the heads (NePu: 256).
        head_blocks: residual blocks per head (NePu: 5).
        shared_head: one head for all 5 outputs instead of NePu's three.
    """

    def __init__(
        self,
        features: int,
        latent: int,
        radius: float,
        width: int = 64,
        n_blocks_2d: int = 3,
        k_2d: int = 8,
        k: int = 20,
        n_freq: int = 5,
        hidden: int | None = None,
        groups: int | None = None,
        vca_mode: str = "factorised",
        head_hidden: int = 64,
        head_blocks: int = 3,
        shared_head: bool = False,
    ) -> None:
        super().__init__()
        self.radius, self.k, self.n_freq = float(radius), k, n_freq
        self.embed = nn.Identity() if features == width else nn.Linear(features, width)
        self.down = nn.Linear(latent, width)
        self.blocks_2d = nn.ModuleList(
            PointTransformerBlock(width, 3, k=k_2d if i == 0 else 0, n_freq=n_freq)
            for i in range(n_blocks_2d)
        )
        self.vca = VectorCrossAttention(width, width, rel_dim=2, abs_dim=1, k=k, n_freq=n_freq,
                                        hidden=hidden, groups=groups, mode=vca_mode)
        self.shared_head = shared_head
        if shared_head:
            self.heads = nn.ModuleList([RenderHead(width, head_hidden, head_blocks, 5)])
        else:
            self.heads = nn.ModuleList(
                RenderHead(width, head_hidden, head_blocks, c) for c in (1, 1, 3)
            )

    def prepare(
        self, keypoints: Tensor, features: Tensor, z: Tensor, camera: CameraBatch
    ) -> RenderContext:
        """Everything that does not depend on the query pixel.

        Args:
            keypoints: world keypoints, (B, K, 3).
            features: keypoint features f, (B, K, d_f).
            z: global code, (B, d_z).
            camera: per-item camera tensors (see :func:`view_frame`).
        """
        frame = view_frame(keypoints, camera, self.radius)
        x = self.embed(features)
        for block in self.blocks_2d:
            x = block(frame.positions, x)
        pos = frame.positions
        return RenderContext(frame, self.vca.prepare(self.down(z), x, pos[..., :2], pos[..., 2:]))

    def query(
        self, ctx: RenderContext, uv: Tensor, outputs: Collection[str] = OUTPUTS
    ) -> dict[str, Tensor]:
        """Render query pixels.

        Args:
            ctx: from :meth:`prepare`.
            uv: query pixels (B, Q, 2), same convention as :mod:`nsd.cameras.projection`.
            outputs: which of :data:`OUTPUTS` to render. With separate heads
                (``shared_head=False``) only their heads run: inverse rendering asks
                for ``logit`` alone, training for ``logit`` at the silhouette points
                and ``depth``, ``nnopcs`` at the in-mask points.

        Returns:
            the requested of ``logit`` (B, Q) silhouette logit, ``depth_norm`` (B, Q)
            normalised depth :math:`\\hat d` with ``depth`` (B, Q) camera depth Z,
            ``nnopcs`` (B, Q, 3) (unclamped).
        """
        unknown = set(outputs) - set(OUTPUTS)
        if unknown or not outputs:
            raise ValueError(f"outputs must be a non-empty subset of {OUTPUTS}, got {outputs}")
        y = self.vca(ctx.prepared, to_frame(uv, ctx.frame))
        if self.shared_head:
            out = self.heads[0](y)
            parts = {"logit": out[..., 0], "depth": out[..., 1], "nnopcs": out[..., 2:5]}
        else:
            parts = {name: head(y) for name, head in zip(OUTPUTS, self.heads, strict=True)
                     if name in outputs}
            parts = {k: v[..., 0] if k != "nnopcs" else v for k, v in parts.items()}
        res = {}
        if "logit" in outputs:
            res["logit"] = parts["logit"]
        if "depth" in outputs:
            res["depth_norm"] = parts["depth"]
            res["depth"] = ctx.frame.depth_ref[:, None] + self.radius * parts["depth"]
        if "nnopcs" in outputs:
            res["nnopcs"] = parts["nnopcs"]
        return res

    def forward(
        self, keypoints: Tensor, features: Tensor, z: Tensor, camera: CameraBatch,
        uv: Tensor,
    ) -> dict[str, Tensor]:
        """:meth:`prepare` then :meth:`query`."""
        return self.query(self.prepare(keypoints, features, z, camera), uv)
