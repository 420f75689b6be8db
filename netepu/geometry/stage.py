"""The geometry stage of ``netepu-train``: NePu's composite loss on sampled points.

A :class:`GeometryTask` is a :class:`nsd.core.trainer.TrainTask`: per step it draws
``batch_size`` training views (:func:`netepu.geometry.data.sample_batch`), perturbs
their keypoints with Gaussian noise (``keypoint_noise`` scene units, NePu's
augmentation), encodes them to ``z``, renders the silhouette points and the
in-mask points of each view from the perturbed keypoints and the decoded
features, and returns the weighted loss of :mod:`netepu.geometry.losses`. By default
the render losses stop at the feature decoder (``render_grad_to_encoder``,
see :meth:`netepu.geometry.model.GeometryModel.encode`): trained jointly as in NePu,
they swamped the keypoint term in the encoder and ``z`` collapsed to a code
that no longer held the pose (keypoint error stuck at the mean pose's). Evaluation
renders full maps of the held-out views (:mod:`netepu.geometry.evaluation`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn

from netepu.geometry.data import GeometryData, build_geometry_data, sample_batch
from netepu.geometry.evaluation import comparison_grid, evaluate_views, render_view_set
from netepu.geometry.losses import (
    GeometryLossWeights,
    depth_loss,
    geometry_loss,
    keypoint_loss,
    latent_loss,
    nnopcs_loss,
    silhouette_loss,
)
from netepu.geometry.maps import MapSettings
from netepu.geometry.model import GeometryModel, build_geometry_model
from nsd.core.config import ConfigSection
from nsd.core.device import move, on_cpu
from nsd.core.errors import ConfigError

__all__ = ["GeometryStageConfig", "GeometryTask", "build_geometry_stage"]

log = logging.getLogger(__name__)


@dataclass
class GeometryStageConfig(ConfigSection):
    """Settings of the geometry stage (``netepu.optim``, ``netepu.points``, ``netepu.eval``)."""

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml, section `netepu`
    KEY: ClassVar[str] = "netepu"

    batch_size: int
    lr: float
    weight_decay: float
    lr_decay: float
    lr_decay_every: int
    near: int
    far: int
    foreground: int
    keypoint_noise: float
    render_grad_to_encoder: bool
    eval_views: int

    @classmethod
    def default_mapping(cls) -> dict[str, Any]:
        """The shipped ``netepu.optim``, ``netepu.points`` and ``netepu.eval`` sections."""
        net = super().default_mapping()
        return {**net["optim"], **net["points"], **net["eval"]}

    @classmethod
    def from_mapping(cls, *sections: Mapping[str, Any]) -> GeometryStageConfig:
        """From the stage's sections; keys they lack take the shipped defaults."""
        values: dict[str, Any] = {}
        for sec in sections:
            values.update(sec)
        return cls.defaults(**values)

    def validate(self) -> None:
        if self.batch_size < 1 or min(self.near + self.far, self.foreground) < 1:
            raise ConfigError("netepu: batch_size and point counts must be >= 1")


class GeometryTask:
    """Model + data + losses of the geometry stage (see the module docstring).

    Args:
        model: the geometry model.
        data: training pools and evaluation views.
        cfg: stage settings.
        weights: loss weights.
        render: how evaluation renders full maps.
    """

    def __init__(
        self,
        model: GeometryModel,
        data: GeometryData,
        cfg: GeometryStageConfig,
        weights: GeometryLossWeights,
        render: MapSettings,
    ) -> None:
        self.model, self.data, self.cfg, self.weights, self.render = (
            model, data, cfg, weights, render)
        pose = [*model.encoder.parameters(), *model.decoder.mlp_pos.parameters()]
        ids = {id(p) for p in pose}
        render = [p for p in model.parameters() if id(p) not in ids]
        self.opts = {
            name: torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
            for name, params in (("pose", pose), ("render", render))
        }
        self.scheds = {}
        if cfg.lr_decay_every > 0:
            self.scheds = {name: torch.optim.lr_scheduler.StepLR(o, cfg.lr_decay_every,
                                                                 cfg.lr_decay)
                           for name, o in self.opts.items()}

    device = torch.device("cpu")  # where training steps run (:meth:`to`)

    def to(self, device: torch.device) -> GeometryTask:
        """Train on ``device`` (evaluation and grids stay on the CPU)."""
        self.device = device
        self.model.to(device)
        return self

    def modules(self) -> dict[str, nn.Module]:
        return {"geometry": self.model}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Two AdamW optimisers, so that the trainer clips their gradients apart.

        ``pose``: encoder and keypoint-position MLP (keypoint and latent losses);
        ``render``: feature decoder and renderer (render losses). One global
        clip would scale the small keypoint gradients by the render
        gradients' norm (~30 early on) and stall the pose code.
        """
        return self.opts

    def schedulers(self) -> dict[str, Any]:
        return self.scheds

    def losses(self, batch: dict[str, Any], rng: np.random.Generator) -> dict[str, Tensor]:
        """Loss terms of one batch (see :mod:`netepu.geometry.losses`)."""
        m, r = self.model, self.model.radius
        kps = batch["keypoints"]
        noise = torch.from_numpy(rng.standard_normal(kps.shape)).to(kps)
        noisy = kps + self.cfg.keypoint_noise * noise
        reach = self.cfg.render_grad_to_encoder
        code = m.encode(noisy, features_reach_encoder=reach)
        # the renderer's query and global token come from z as well
        render_code = code if reach else replace(code, z=code.z.detach())
        ctx = m.prepare(render_code, batch["camera"], keypoints=noisy)
        # each head only where it is supervised (separate heads: the others do not run)
        sil = m.query(ctx, batch["sil_uv"], ("logit",))
        fg = m.query(ctx, batch["fg_uv"], ("depth", "nnopcs"))
        target_depth = (batch["fg_depth"] - ctx.frame.depth_ref[:, None]) / r
        terms = {
            "silhouette": silhouette_loss(sil["logit"], batch["sil_label"]),
            "keypoints": keypoint_loss(code.keypoints / (2 * r), kps / (2 * r)),
            "depth": depth_loss(fg["depth_norm"], target_depth),
            "nnopcs": nnopcs_loss(fg["nnopcs"], batch["fg_nnopcs"]),
            "latent": latent_loss(code.z),
        }
        return geometry_loss(terms, self.weights)

    def training_step(self, step: int, rng: np.random.Generator) -> dict[str, Tensor]:
        c = self.cfg
        batch = sample_batch(self.data, rng, c.batch_size, c.near, c.far, c.foreground)
        return self.losses(move(batch, self.device), rng)

    def _eval_sets(self):
        for name, views in self.data.evaluation.items():
            n = min(self.cfg.eval_views, len(views))
            idx = np.linspace(0, len(views) - 1, n).round().astype(int).tolist()
            yield name, views.subset(idx)

    def evaluate(self, step: int) -> dict[str, float]:
        out: dict[str, float] = {}
        with on_cpu(self.model):
            for name, views in self._eval_sets():
                out.update(evaluate_views(self.model, views, self.render, prefix=f"{name}/"))
        return out

    def image_grids(self, step: int) -> dict[str, np.ndarray]:
        grids = {}
        self.model.eval()
        with on_cpu(self.model):
            for name, views in self._eval_sets():
                sub = views.subset(list(range(min(4, len(views)))))
                grids[f"geometry_{name}"] = comparison_grid(
                    render_view_set(self.model, sub, self.render), sub)
        self.model.train()
        return grids


def build_geometry_stage(cfg: DictConfig) -> tuple[Any, dict[str, Any]]:
    """The geometry task of ``cfg``; returns it and config values found at build time."""

    net = OmegaConf.to_container(cfg.netepu, resolve=True)
    data = build_geometry_data(net["data"], progress=log.info)
    model = build_geometry_model(net["model"], data.config.n_keypoints, data.config.radius)
    stage = GeometryStageConfig.from_mapping(net["optim"], net["points"], net["eval"])
    try:
        weights = GeometryLossWeights.from_config(net["loss"])
        render = MapSettings.from_config(net["render"])
        render.validate()
    except (TypeError, ValueError) as e:
        raise ConfigError(f"netepu.loss / netepu.render: {e}") from e
    task = GeometryTask(model, data, stage, weights, render)
    return task, {"n_keypoints": data.config.n_keypoints}
