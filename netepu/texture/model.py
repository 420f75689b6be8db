r"""NeTePu's texture pipeline: a texture VAE whose decoder is a keypoint-driven colour renderer.

NeTePu sec. 3.2 (fig. 1 bottom), with the geometry pipeline frozen.

Public API (what the end-to-end pipeline calls)::

    texture_codes(texture, geometry, image, mask, keypoints, camera, window=None) -> Tensor
        # image (B, H, W, 3) float in [0, 1] or uint8: full frames or square crops
        # mask (B, H, W) bool: the subject's VISIBLE pixels (only they are read)
        # keypoints (B, K, 3) world; camera: K, R, t[, dist] with batch B
        # window (B, 3): (x0, y0, side) of a square crop in the camera's native
        #   pixels (pixel edges, as nsd.io.crops); None: image is the full frame
        # -> mu, (B, d_z): the texture code (the embedding) of each subject
    encode_texture(texture, image, mask, nnopcs) -> Tensor
        # the same from a precomputed (predicted) NNOPCS map (B, H, W, 3)

Both are ``torch.no_grad`` and put nothing but the code together; the model is
loaded with :func:`load_texture_model` from a ``netepu-train stage=texture``
checkpoint, which holds the frozen geometry model too.

Encoder input (:func:`encoder_crops`)
    The subject's visible pixels are cut out of the image with the square
    window around the mask's box (side ``max(w, h) (1 + 2 margin)``, as
    :func:`nsd.io.crops.square_crop_box`) and resampled to ``S x S``
    (``crop_size``): the masked image :math:`I \cdot M` and the mask are
    sampled bilinearly and divided, :math:`\tilde I = \mathrm{bilin}(I M) /
    \mathrm{bilin}(M)` where :math:`\mathrm{bilin}(M) > 1/2` and 0 elsewhere,
    so no pixel outside the mask reaches the encoder. The NNOPCS map is
    rendered by the frozen geometry model directly at the in-mask crop pixels
    (the renderer answers any query pixel), i.e. the encoder always sees
    *predicted* NNOPCS, in training and at inference (the reference trains on
    ground truth and tests on predictions). Channels: masked RGB, mask,
    NNOPCS (7; the RGB-only variant: 4).

Encoder (:class:`TextureEncoder`)
    A ResNet-like CNN (BatchNorm, ReLU; ``2 x len(widths)`` basic blocks, ~20
    convolutions, NeTePu: 23) with global average pooling and two dense
    layers giving :math:`\mu` and :math:`\log\sigma^2`. Training samples
    :math:`z = \mu + \sigma \epsilon` (:func:`reparameterise`); inference
    uses :math:`\mu` (the reference stores a sample).

Decoder and renderer (:class:`TextureDecoder`, :class:`ColourRenderer`)
    :math:`z_{texture} \mapsto f_{texture} \in \mathbb{R}^{K \times d_f}`
    (an MLP, eq. 3). The colour renderer is the geometry renderer's class
    (:class:`netepu.geometry.renderer.NeuralRenderer2D`: same view frame, 2D blocks
    and factorised VCA) with a 3-channel colour head; its keypoint features
    are the frozen geometry features :math:`f` concatenated with
    :math:`f_{texture}` and its global code is :math:`[z, z_{texture}]`.
    The ablation without local texture features (``local_features: false``)
    keeps only :math:`f`, so the texture reaches the renderer through the
    global token alone. Only foreground pixels are ever rendered.

Re-identification embedding (:meth:`TextureModel.reid_embedding`)
    :math:`\mu` renders; for retrieval, :math:`u = \mu` (or, with
    ``reid_colour``, :math:`u = [\mu, c]` with the crop's colour statistics
    :math:`c`, :func:`netepu.reid.metrics.colour_statistics`) is mapped by a
    within-class whitening :math:`e = (u - m) P`
    (:func:`netepu.reid.metrics.within_class_whitening`) that the texture stage fits on
    its training codes after training and stores in the model (buffers
    ``reid_mean``, ``reid_projection``; the identity for models without it).

Loss (:func:`texture_loss`): :math:`\lambda_{col}` MSE of colour on in-mask
points + :math:`\lambda_{KLD}` KLD (eq. 8; defaults 5 and 1e-8), with
:math:`\mathrm{KLD} = -\tfrac12 \sum_d (1 + \log\sigma_d^2 - \mu_d^2 - \sigma_d^2)`
averaged over the batch.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from netepu.geometry.model import GeometryModel, build_geometry_model
from netepu.geometry.renderer import NeuralRenderer2D, RenderContext, RenderHead, to_frame
from nsd.core.errors import CheckpointError, ConfigError
from nsd.io.crops import square_crop_box
from nsd.ops.boxes import mask_boxes_xyxy

__all__ = [
    "ColourRenderer",
    "TextureConfig",
    "TextureDecoder",
    "TextureEncoder",
    "TextureModel",
    "build_texture_model",
    "code_contrast_loss",
    "crop_grid",
    "crop_windows",
    "encode_texture",
    "encoder_crops",
    "kld",
    "load_texture_model",
    "query_masked",
    "reparameterise",
    "sample_masked",
    "texture_codes",
    "texture_loss",
]


# ----------------------------------------------------------------------------- config
@dataclass
class TextureConfig:
    """The ``netepu.texture.model`` config (every field commented in the YAML file)."""

    latent: int = 128
    features: int = 64
    use_nnopcs: bool = True
    use_normals: bool = False
    local_features: bool = True
    crop_size: int = 64
    crop_margin: float = 0.1
    widths: list[int] = field(default_factory=lambda: [16, 32, 64, 128])
    blocks_per_stage: int = 2
    dense_hidden: int = 256
    decoder_hidden: int = 256
    renderer: dict[str, Any] = field(default_factory=dict)
    reid_colour: bool = False

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> TextureConfig:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - names)
        if unknown:
            raise ConfigError(
                f"netepu.texture.model: unknown keys {unknown}; known {sorted(names)}"
            )
        c = cls(**dict(cfg))
        if c.crop_size < 16 or c.latent < 1 or c.features < 1 or c.crop_margin < 0:
            raise ConfigError(
                "netepu.texture.model: crop_size >= 16, latent and features >= 1, crop_margin >= 0"
            )
        if c.use_normals and not c.use_nnopcs:
            raise ConfigError(
                "netepu.texture.model.use_normals needs use_nnopcs: the normals come from the "
                "geometry model's depth, rendered with the NNOPCS map (an RGB-only model: "
                "use_nnopcs=false use_normals=false)"
            )
        return c

    @property
    def reid_dims(self) -> int:
        """Length of the re-identification input: d_z [+ the colour statistics]."""
        from netepu.reid.metrics import COLOUR_STATISTICS

        return self.latent + (COLOUR_STATISTICS if self.reid_colour else 0)

    @property
    def surface_channels(self) -> int:
        """Channels of the rendered surface crop: NNOPCS (3) [+ world normals (3)]."""
        return (3 if self.use_nnopcs else 0) + (3 if self.use_normals else 0)


# ----------------------------------------------------------------------------- crops
def crop_windows(mask: Tensor, margin: float) -> Tensor:
    """Square windows around the masks' boxes.

    Args:
        mask: (B, H, W) bool.
        margin: enlargement per side, as a fraction of the box's longer side.

    Returns:
        (B, 3) ``(x0, y0, side)`` in pixels (pixel edges), float64.

    Raises:
        ValueError: a mask is empty (names the batch items).
    """
    empty = ~mask.flatten(1).any(1)
    if empty.any():
        raise ValueError(
            f"texture code: empty visible masks at batch items "
            f"{torch.nonzero(empty).flatten().tolist()}"
        )
    boxes = mask_boxes_xyxy(mask).double()
    return torch.tensor(
        [square_crop_box([b[0], b[1], b[2] - b[0], b[3] - b[1]], margin) for b in boxes.tolist()],
        dtype=torch.float64,
    )


def crop_grid(window: Tensor, size: int) -> Tensor:
    """Pixel centres of an ``size x size`` grid over square windows.

    Pixel ``(u, v)`` of the grid (centre at integers) sits at
    ``x = x0 + (u + 0.5) side / size - 0.5`` (and the same for y).

    Args:
        window: (B, 3) ``(x0, y0, side)``.
        size: S.

    Returns:
        (B, S, S, 2) ``(x, y)`` pixel coordinates, float64.
    """
    t = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    x = window[:, None, 0] + t[None] * window[:, None, 2] - 0.5  # (B, S)
    y = window[:, None, 1] + t[None] * window[:, None, 2] - 0.5
    return torch.stack(torch.broadcast_tensors(x[:, None, :], y[:, :, None]), -1)


def sample_masked(values: Tensor, mask: Tensor, grid: Tensor) -> tuple[Tensor, Tensor]:
    r"""Bilinear samples of masked values that never read pixels outside the mask.

    :math:`\mathrm{bilin}(v M) / \mathrm{bilin}(M)` where :math:`\mathrm{bilin}(M) > 1/2`,
    0 elsewhere (outside the image counts as outside the mask).

    Args:
        values: (B, H, W, C) float.
        mask: (B, H, W) bool.
        grid: (B, S, S, 2) pixel coordinates (centre of pixel i at i).

    Returns:
        ``(sampled, inside)``: (B, S, S, C) and (B, S, S) bool.
    """
    _, H, W, C = values.shape
    m = mask.to(values.dtype)[:, None]
    x = torch.cat([(values * mask[..., None]).permute(0, 3, 1, 2), m], 1)
    g = grid.to(values.dtype)
    g = torch.stack([(g[..., 0] + 0.5) / W * 2 - 1, (g[..., 1] + 0.5) / H * 2 - 1], -1)
    s = F.grid_sample(x, g, mode="bilinear", padding_mode="zeros", align_corners=False)
    weight = s[:, C]
    inside = weight > 0.5
    out = torch.where(inside[:, None], s[:, :C] / weight.clamp(min=1e-6)[:, None], 0.0)
    return out.permute(0, 2, 3, 1), inside


def query_masked(query: Callable[[Tensor], Tensor], uv: Tensor, keep: Tensor) -> Tensor:
    """Evaluate ``query`` only at kept pixels (padded per batch item), zeros elsewhere.

    Args:
        query: ``uv (B, Q, 2) -> (B, Q, C)``.
        uv: (B, N, 2) pixels.
        keep: (B, N) bool.

    Returns:
        (B, N, C).
    """
    B, N = keep.shape
    counts = keep.sum(1)
    n = max(int(counts.max()), 1) if B else 1
    order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, :n]  # kept first
    pts = torch.gather(uv, 1, order[..., None].expand(B, n, 2))
    vals = query(pts)
    valid = torch.arange(n)[None] < counts[:, None]
    vals = vals * valid[..., None]
    out = vals.new_zeros(B, N, vals.shape[-1])
    return out.scatter(1, order[..., None].expand(B, n, vals.shape[-1]), vals)


# ----------------------------------------------------------------------------- networks
class _BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.b1 = nn.BatchNorm2d(cout)
        self.c2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.b2 = nn.BatchNorm2d(cout)
        self.skip = (
            nn.Identity()
            if stride == 1 and cin == cout
            else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
        )

    def forward(self, x: Tensor) -> Tensor:
        y = self.b2(self.c2(torch.relu(self.b1(self.c1(x)))))
        return torch.relu(y + self.skip(x))


class TextureEncoder(nn.Module):
    """CNN (masked RGB, mask[, NNOPCS]) crop -> (mu, logvar) (eq. 2).

    Args:
        in_channels: 7 with NNOPCS, 4 without.
        latent: d_z.
        widths: channels of the stages (each halves the resolution after the first).
        blocks_per_stage: basic blocks per stage.
        dense_hidden: width of the first dense layer.

    Shape:
        (B, C_in, S, S) -> ((B, d_z), (B, d_z)).
    """

    def __init__(
        self,
        in_channels: int,
        latent: int,
        widths: list[int],
        blocks_per_stage: int = 2,
        dense_hidden: int = 256,
    ) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, widths[0], 3, 1, 1, bias=False),
            nn.BatchNorm2d(widths[0]),
            nn.ReLU(),
        )
        layers, cin = [], widths[0]
        for i, w in enumerate(widths):
            for j in range(blocks_per_stage):
                layers.append(_BasicBlock(cin, w, 2 if (j == 0 and i > 0) else 1))
                cin = w
        self.blocks = nn.Sequential(*layers)
        self.dense = nn.Sequential(
            nn.Linear(cin, dense_hidden), nn.ReLU(), nn.Linear(dense_hidden, 2 * latent)
        )
        self.latent = latent

    def features(self, x: Tensor) -> Tensor:
        """Pooled CNN features, (B, widths[-1])."""
        return self.blocks(self.stem(x)).mean(dim=(2, 3))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        out = self.dense(self.features(x))
        return out[:, : self.latent], out[:, self.latent :]


class TextureDecoder(nn.Module):
    """z_texture (B, d_z) -> per-keypoint texture features f_texture (B, K, d_f) (eq. 3)."""

    def __init__(self, latent: int, n_keypoints: int, features: int, hidden: int = 256) -> None:
        super().__init__()
        self.k, self.f = n_keypoints, features
        self.mlp = nn.Sequential(
            nn.Linear(latent, hidden), nn.ReLU(), nn.Linear(hidden, n_keypoints * features)
        )

    def forward(self, z: Tensor) -> Tensor:
        return self.mlp(z).view(-1, self.k, self.f)


class ColourRenderer(NeuralRenderer2D):
    """The geometry renderer's architecture with a 3-channel colour head (eq. 4).

    Same arguments as :class:`NeuralRenderer2D` (``shared_head`` is ignored).
    :meth:`query` returns ``{"colour": (B, Q, 3)}`` (unclamped).
    """

    def __init__(self, features: int, latent: int, radius: float, **kw: Any) -> None:
        kw = {k: v for k, v in kw.items() if k != "shared_head"}
        super().__init__(features, latent, radius, **kw)
        width = self.down.out_features
        hh, hb = kw.get("head_hidden", 64), kw.get("head_blocks", 3)
        self.heads = nn.ModuleList([RenderHead(width, hh, hb, 3)])

    def query(self, ctx: RenderContext, uv: Tensor) -> dict[str, Tensor]:
        y = self.vca(ctx.prepared, to_frame(uv, ctx.frame))
        return {"colour": self.heads[0](y)}


# ----------------------------------------------------------------------------- losses
def reparameterise(mu: Tensor, logvar: Tensor, noise: Tensor | None = None) -> Tensor:
    """z = mu + exp(logvar / 2) * eps, eps ~ N(0, I) (or ``noise``); shapes (B, d_z)."""
    eps = torch.randn_like(mu) if noise is None else noise
    return mu + torch.exp(0.5 * logvar) * eps


def kld(mu: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)) summed over dimensions, mean over the batch; scalar."""
    return (-0.5 * (1 + logvar - mu.square() - logvar.exp()).sum(-1)).mean()


def code_contrast_loss(mu: Tensor, partner: Tensor, same: Tensor, temperature: float) -> Tensor:
    r"""Supervised contrastive loss between texture codes of two views of the same batch.

    With unit codes :math:`u_i = \mu_i / \lVert\mu_i\rVert` of the batch and
    :math:`u'_j` of the partner views (each another pose and camera of the
    texture of row :math:`j`), and :math:`P(i) = \{j : \text{same}_{ij}\}`,

    .. math::
        L = -\frac{1}{B}\sum_i \log
            \frac{\sum_{j \in P(i)} e^{u_i \cdot u'_j / \tau}}
                  {\sum_{j} e^{u_i \cdot u'_j / \tau}} ,

    computed with log-sum-exp. It pulls the codes of one texture seen in
    different views together and pushes those of other textures apart: what
    re-identification needs, and what a reconstruction loss alone does not ask.

    Args:
        mu: codes (B, D); partner: codes (B, D) of the partner views.
        same: (B, B) bool, row i and partner j show the same texture (the
            diagonal is True).
        temperature: :math:`\tau` > 0.

    Returns:
        Scalar.
    """
    if temperature <= 0:
        raise ValueError(f"code_contrast_loss: temperature must be > 0, got {temperature}")
    u = F.normalize(mu, dim=-1, eps=1e-12)
    v = F.normalize(partner, dim=-1, eps=1e-12)
    logits = u @ v.T / temperature
    positive = logits.masked_fill(~same, float("-inf"))
    return (torch.logsumexp(logits, -1) - torch.logsumexp(positive, -1)).mean()


def texture_loss(
    colour: Tensor,
    target: Tensor,
    mu: Tensor,
    logvar: Tensor,
    w_colour: float = 5.0,
    w_kld: float = 1e-8,
) -> dict[str, Tensor]:
    """Eq. 8: ``w_colour`` MSE(colour (B, P, 3), target) + ``w_kld`` KLD; returns the terms."""
    col = F.mse_loss(colour, target)
    k = kld(mu, logvar)
    return {"colour": col, "kld": k, "loss": w_colour * col + w_kld * k}


# ----------------------------------------------------------------------------- model
class TextureModel(nn.Module):
    """Texture encoder + decoder + colour renderer of one species (geometry lives apart).

    Args:
        cfg: the model config.
        n_keypoints: K.
        geometry_features, geometry_latent: d_f and d_z of the geometry model.
        radius: body radius r of the species.
    """

    def __init__(
        self,
        cfg: TextureConfig,
        n_keypoints: int,
        geometry_features: int,
        geometry_latent: int,
        radius: float,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = TextureEncoder(
            4 + cfg.surface_channels,
            cfg.latent,
            list(cfg.widths),
            cfg.blocks_per_stage,
            cfg.dense_hidden,
        )
        self.decoder = (
            TextureDecoder(cfg.latent, n_keypoints, cfg.features, cfg.decoder_hidden)
            if cfg.local_features
            else None
        )
        feats = geometry_features + (cfg.features if cfg.local_features else 0)
        try:
            self.renderer = ColourRenderer(
                feats, geometry_latent + cfg.latent, radius, **dict(cfg.renderer)
            )
        except TypeError as e:
            raise ConfigError(f"netepu.texture.model.renderer: {e}") from e
        # re-identification embedding (u - reid_mean) @ reid_projection of the input
        # u = [mu, colour statistics] (netepu.reid's within-class whitening, fitted after
        # training); the identity until then
        self.register_buffer("reid_mean", torch.zeros(cfg.reid_dims))
        self.register_buffer("reid_projection", torch.eye(cfg.reid_dims))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        d = self.cfg.reid_dims  # checkpoints from before the whitening: the identity map
        state_dict.setdefault(prefix + "reid_mean", torch.zeros(d))
        state_dict.setdefault(prefix + "reid_projection", torch.eye(d))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def reid_input(
        self, mu: Tensor, rgb: Tensor | None = None, inside: Tensor | None = None
    ) -> Tensor:
        """What the re-identification whitening reads: mu (B, d_z), with ``reid_colour``
        followed by :func:`netepu.reid.metrics.colour_statistics` of the crop that gave mu (rgb
        (B, S, S, 3) in [0, 1], inside (B, S, S) bool): (B, cfg.reid_dims)."""
        if not self.cfg.reid_colour:
            return mu
        if rgb is None or inside is None:
            raise ValueError(
                "this texture model re-identifies with colour statistics: pass the crop"
            )
        from netepu.reid.metrics import colour_statistics

        return torch.cat([mu, colour_statistics(rgb, inside).to(mu.dtype)], -1)

    def reid_embedding(
        self, mu: Tensor, rgb: Tensor | None = None, inside: Tensor | None = None
    ) -> Tensor:
        """Re-identification embedding of texture codes mu (B, d_z) encoded from the crop
        rgb, inside (needed with ``reid_colour``; :meth:`reid_input`): (B, cfg.reid_dims)."""
        return self.whiten_reid(self.reid_input(mu, rgb, inside))

    def whiten_reid(self, u: Tensor) -> Tensor:
        """The stored whitening of re-id inputs u (B, reid_dims): (u - m) P, (B, reid_dims)."""
        return (u - self.reid_mean.to(u.dtype)) @ self.reid_projection.to(u.dtype)

    @staticmethod
    def crop_colours(x: Tensor) -> tuple[Tensor, Tensor]:
        """The crop colours (B, S, S, 3) and mask (B, S, S) bool of an encoder input x
        (B, C_in, S, S) (:meth:`encoder_input`)."""
        return x[:, :3].permute(0, 2, 3, 1), x[:, 3] > 0.5

    def set_reid_whitening(self, mean: Tensor | Any, projection: Tensor | Any) -> None:
        """Store a whitening ``(m (D,), P (D, D))`` of the re-id input, D = ``cfg.reid_dims``.

        See :func:`netepu.reid.metrics.within_class_whitening`.
        """
        m = torch.as_tensor(mean, dtype=self.reid_mean.dtype)
        p = torch.as_tensor(projection, dtype=self.reid_projection.dtype)
        if m.shape != self.reid_mean.shape or p.shape != self.reid_projection.shape:
            raise ValueError(
                f"reid whitening: want shapes {tuple(self.reid_mean.shape)} and "
                f"{tuple(self.reid_projection.shape)}, got {tuple(m.shape)} and {tuple(p.shape)}"
            )
        self.reid_mean.copy_(m)
        self.reid_projection.copy_(p)

    def encoder_input(self, rgb: Tensor, inside: Tensor, nnopcs: Tensor | None) -> Tensor:
        """Crops (B, S, S, 3), (B, S, S) bool, surface (B, S, S, C_s) -> encoder input
        (B, C_in, S, S); C_s = ``cfg.surface_channels`` (NNOPCS [+ world normals])."""
        parts = [rgb, inside[..., None].to(rgb.dtype)]
        if self.cfg.use_nnopcs:
            if nnopcs is None:
                raise ValueError("this texture model reads NNOPCS maps; pass them")
            parts.append(nnopcs * inside[..., None])
        return torch.cat(parts, -1).permute(0, 3, 1, 2).contiguous()

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Encoder input (B, C_in, S, S) -> (mu, logvar), each (B, d_z)."""
        return self.encoder(x)

    def prepare(
        self,
        z_texture: Tensor,
        geometry_z: Tensor,
        geometry_features: Tensor,
        keypoints: Tensor,
        camera: dict[str, Tensor],
    ) -> RenderContext:
        """Per-view colour render context.

        Args:
            z_texture: (B, d_z) texture codes.
            geometry_z, geometry_features: the frozen geometry code, (B, d_zg), (B, K, d_f).
            keypoints: world keypoints (B, K, 3) that drive the render.
            camera: per-view camera tensors (batch B).
        """
        feats = geometry_features
        if self.decoder is not None:
            feats = torch.cat([feats, self.decoder(z_texture)], -1)
        return self.renderer.prepare(
            keypoints, feats, torch.cat([geometry_z, z_texture], -1), camera
        )

    def query(self, ctx: RenderContext, uv: Tensor) -> Tensor:
        """Colour at query pixels (B, Q, 2) -> (B, Q, 3) (unclamped)."""
        return self.renderer.query(ctx, uv)["colour"]


def build_texture_model(
    cfg: Mapping[str, Any] | TextureConfig, geometry: GeometryModel
) -> TextureModel:
    """Texture model for a geometry model (sizes taken from it)."""
    if not isinstance(cfg, TextureConfig):
        cfg = TextureConfig.from_mapping(cfg)
    return TextureModel(
        cfg,
        geometry.n_keypoints,
        geometry.decoder.n_features,
        geometry.renderer.down.in_features,
        geometry.radius,
    )


def load_texture_model(
    path: str | os.PathLike,
) -> tuple[TextureModel, GeometryModel, dict[str, Any]]:
    """Load ``(texture, geometry, config)`` from a ``netepu-train stage=texture`` checkpoint.

    Both models are returned in eval mode.
    """
    from nsd.core.trainer import load_checkpoint

    state = load_checkpoint(path)
    config = state.get("config") or {}
    try:
        net = config["netepu"]
        geometry = build_geometry_model(
            net["model"], int(net["data"]["n_keypoints"]), float(net["data"]["radius"])
        )
        geometry.load_state_dict(state["modules"]["geometry"])
        texture = build_texture_model(net["texture"]["model"], geometry)
        texture.load_state_dict(state["modules"]["texture"])
    except (KeyError, RuntimeError, TypeError) as e:
        raise CheckpointError(f"{path} is not a NeTePu texture checkpoint: {e}") from e
    return texture.eval(), geometry.eval(), config


# ----------------------------------------------------------------------------- inference
def _as_float_image(image: Tensor) -> Tensor:
    if image.dtype == torch.uint8:
        return image.float() / 255.0
    return image.float()


def predicted_nnopcs(
    geometry: GeometryModel, keypoints: Tensor, camera: dict[str, Tensor], uv: Tensor, keep: Tensor
) -> Tensor:
    """NNOPCS rendered by the geometry model at kept pixels, clamped to [0, 1].

    Args:
        keypoints: (B, K, 3) world; camera: batch B.
        uv: (B, N, 2) pixels of the camera; keep: (B, N) bool.

    Returns:
        (B, N, 3), zeros where not kept.
    """
    ctx = _posed_context(geometry, keypoints, camera)
    out = query_masked(lambda q: geometry.query(ctx, q)["nnopcs"], uv, keep)
    return out.clamp(0, 1)


def _posed_context(geometry: GeometryModel, keypoints: Tensor, camera: dict[str, Tensor]):
    """The geometry model's query context for keypoints (B, K, 3) seen by cameras (batch B)."""
    return geometry.prepare(geometry.encode(keypoints), camera, keypoints=keypoints)


def surface_normals(depth: Tensor, uv: Tensor, inside: Tensor, K: Tensor, R: Tensor) -> Tensor:
    r"""World-space unit normals of a depth crop on a regular pixel grid.

    Each crop pixel :math:`(u, v)` with camera depth :math:`Z` is back-projected,
    :math:`X = Z\, K^{-1} (u, v, 1)^\top` (lens distortion ignored: a crop spans a
    few dozen pixels), its tangents are the finite differences of :math:`X` along
    the crop's two axes (the mean of the forward and backward difference where
    both neighbours are inside, the one that is otherwise, none at a pixel with
    no inside neighbour on an axis), and the normal
    :math:`n = \partial_y X \times \partial_x X / \lVert\cdot\rVert`, flipped
    to face the camera (:math:`n \cdot X < 0`), is rotated to the world,
    :math:`n_w = R^\top n` (``R`` world-to-camera). With a light fixed in the
    world, Lambertian shading is a function of :math:`n_w` alone: what lets a
    texture code tell albedo from shading.

    Args:
        depth: (B, S, S) camera depth Z at the crop pixels.
        uv: (B, S, S, 2) their camera pixels (x, y).
        inside: (B, S, S) bool, pixels with a depth.
        K: (B, 3, 3) intrinsics; R: (B, 3, 3) world-to-camera rotation.

    Returns:
        (B, S, S, 3) unit normals; zeros outside or without a tangent on both axes.
    """
    ones = torch.ones_like(depth)
    rays = torch.einsum("bij,bhwj->bhwi", torch.linalg.inv(K), torch.cat([uv, ones[..., None]], -1))
    X = rays * depth[..., None]
    m = inside.to(X.dtype)

    def tangent(dim: int) -> tuple[Tensor, Tensor]:
        """Tangent along grid axis ``dim`` (1: rows, 2: columns) and where it exists."""
        n = X.shape[dim]
        step = X.narrow(dim, 1, n - 1) - X.narrow(dim, 0, n - 1)
        ok = m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1)
        step = step * ok[..., None]
        zero, zero_ok = torch.zeros_like(X.narrow(dim, 0, 1)), torch.zeros_like(m.narrow(dim, 0, 1))
        total = torch.cat([step, zero], dim) + torch.cat([zero, step], dim)  # forward + backward
        count = torch.cat([ok, zero_ok], dim) + torch.cat([zero_ok, ok], dim)
        return total / count.clamp_min(1)[..., None], count > 0

    tx, okx = tangent(2)
    ty, oky = tangent(1)
    n = torch.cross(ty, tx, dim=-1)
    n = n * torch.where((n * X).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(n.dtype)
    n = torch.nn.functional.normalize(n, dim=-1, eps=1e-12)
    world = torch.einsum("bji,bhwj->bhwi", R, n)
    return world * (inside & okx & oky)[..., None].to(X.dtype)


def predicted_surface(
    geometry: GeometryModel,
    keypoints: Tensor,
    camera: dict[str, Tensor],
    uv: Tensor,
    keep: Tensor,
    normals: bool,
) -> Tensor:
    """The geometry model's surface at kept crop pixels: NNOPCS [+ world normals].

    Args:
        keypoints: (B, K, 3) world; camera: batch B.
        uv: (B, S, S, 2) crop pixels of the camera (a regular grid); keep: (B, S, S) bool.
        normals: also :func:`surface_normals` of the rendered depth.

    Returns:
        (B, S, S, 3) or (B, S, S, 6), zeros where not kept.
    """
    B, S1, S2 = keep.shape
    flat_uv, flat_keep = uv.reshape(B, S1 * S2, 2), keep.reshape(B, S1 * S2)
    if not normals:
        return predicted_nnopcs(geometry, keypoints, camera, flat_uv, flat_keep).reshape(
            B, S1, S2, 3
        )
    ctx = _posed_context(geometry, keypoints, camera)

    def both(q: Tensor) -> Tensor:
        out = geometry.query(ctx, q)
        return torch.cat([out["nnopcs"].clamp(0, 1), out["depth"][..., None]], -1)

    out = query_masked(both, flat_uv, flat_keep).reshape(B, S1, S2, 4)
    K, R = camera["K"].to(out.dtype), camera["R"].to(out.dtype)
    n = surface_normals(out[..., 3], uv.to(out.dtype), keep, K, R)
    return torch.cat([out[..., :3], n], -1)


def encoder_crops(
    texture: TextureModel,
    image: Tensor,
    mask: Tensor,
    nnopcs: Tensor | Callable[[Tensor, Tensor], Tensor] | None,
    window: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
    """Cut the encoder's crops (see the module docstring).

    Args:
        texture: the model (crop size and margin).
        image: (B, H, W, 3) float in [0, 1] or uint8.
        mask: (B, H, W) bool visible pixels.
        nnopcs: a map (B, H, W, C_s) sampled like the image, or a function
            ``(uv (B, S, S, 2) camera pixels, keep (B, S, S)) -> (B, S, S, C_s)``
            that renders it at the crop pixels (:func:`predicted_surface`), or None
            (RGB-only models); C_s = ``cfg.surface_channels``.
        window: (B, 3) where ``image`` lies in the camera's native pixels
            (square crops); None: the image is the camera frame.

    Returns:
        ``(rgb, inside, nnopcs, grid)``: (B, S, S, 3), (B, S, S) bool,
        (B, S, S, C_s) or None, and the crop grid (B, S, S, 2) in image pixels.
    """
    img = _as_float_image(image)
    if img.ndim != 4 or img.shape[-1] != 3 or mask.shape != img.shape[:3]:
        raise ValueError(
            f"texture code: image must be (B, H, W, 3) and mask (B, H, W), got "
            f"{tuple(image.shape)} and {tuple(mask.shape)}"
        )
    mask = mask.bool()
    S = texture.cfg.crop_size
    grid = crop_grid(crop_windows(mask, texture.cfg.crop_margin), S)
    rgb, inside = sample_masked(img, mask, grid)
    nn_crop = None
    if texture.cfg.use_nnopcs:
        if nnopcs is None:
            raise ValueError(
                "this texture model reads NNOPCS: pass keypoints and cameras (or a map)"
            )
        if callable(nnopcs):
            cam_grid = grid
            if window is not None:
                H, W = img.shape[1:3]
                w = window.double()
                cam_grid = torch.stack(
                    [
                        w[:, None, None, 0] + (grid[..., 0] + 0.5) * w[:, None, None, 2] / W - 0.5,
                        w[:, None, None, 1] + (grid[..., 1] + 0.5) * w[:, None, None, 2] / H - 0.5,
                    ],
                    -1,
                )
            nn_crop = nnopcs(cam_grid.float(), inside)
        else:
            nn_crop, _ = sample_masked(nnopcs.float(), mask, grid)
        nn_crop = nn_crop * inside[..., None]
    return rgb, inside, nn_crop, grid


@torch.no_grad()
def encode_texture(
    texture: TextureModel, image: Tensor, mask: Tensor, nnopcs: Tensor | None = None
) -> Tensor:
    """Texture codes mu (B, d_z) from images, visible masks and NNOPCS maps (B, H, W, 3).

    ``nnopcs`` should be the geometry model's prediction (as in training);
    None for RGB-only models.
    """
    rgb, inside, nn_crop, _ = encoder_crops(texture, image, mask, nnopcs)
    texture.eval()
    return texture.encode(texture.encoder_input(rgb, inside, nn_crop))[0]


@torch.no_grad()
def texture_codes(
    texture: TextureModel,
    geometry: GeometryModel | None,
    image: Tensor,
    mask: Tensor,
    keypoints: Tensor | None,
    camera: dict[str, Tensor] | None,
    window: Tensor | None = None,
    return_crops: bool = False,
) -> Tensor | tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Texture codes of subjects from their visible pixels (see the module docstring).

    Args:
        texture, geometry: the models of a texture checkpoint (geometry may be
            None for RGB-only models).
        image: (B, H, W, 3) float in [0, 1] or uint8 frames or square crops.
        mask: (B, H, W) bool, the subject's visible pixels; nothing else is read.
        keypoints: (B, K, 3) world keypoints of each subject (None: RGB-only).
        camera: ``K, R, t[, dist]`` with batch B (the camera of each image).
        window: (B, 3) ``(x0, y0, side)`` of square crops in the camera's native
            pixels; None when ``image`` is the camera frame.
        return_crops: also return what the encoder read.

    Returns:
        mu, (B, d_z); with ``return_crops``: ``(mu, rgb (B, S, S, 3), inside (B, S, S),
        surface (B, S, S, C_s) or None)``, the surface being the predicted NNOPCS
        [+ world normals] at the crop pixels.
    """
    render = None
    if texture.cfg.use_nnopcs:
        if geometry is None or keypoints is None or camera is None:
            raise ValueError(
                "texture_codes: this model reads NNOPCS maps and needs the geometry "
                "model, keypoints and cameras"
            )
        geometry.eval()
        kps = keypoints.float()
        cam = {k: v.float() for k, v in camera.items()}

        def render(uv: Tensor, keep: Tensor) -> Tensor:
            return predicted_surface(geometry, kps, cam, uv, keep, texture.cfg.use_normals)

    rgb, inside, nn_crop, _ = encoder_crops(texture, image, mask, render, window)
    texture.eval()
    mu = texture.encode(texture.encoder_input(rgb, inside, nn_crop))[0]
    return (mu, rgb, inside, nn_crop) if return_crops else mu
