"""The texture stage of ``netepu-train``: the texture VAE trained against a frozen geometry model.

``netepu-train stage=texture init_from=<geometry checkpoint>`` builds a
:class:`TextureTask` (:func:`build_texture_stage`): the geometry model and its
data config come from the checkpoint (``init_from``), the texture model from
``netepu.texture.model`` and the multi-texture data from
``netepu.texture.data`` (:mod:`netepu.texture.data`).

Per step: ``batch_size`` random (view, texture) samples; the encoder reads
the masked RGB crop, the mask and the NNOPCS crop *predicted* by the frozen
geometry model (computed once for every view at build time, exactly the
pixels :func:`netepu.texture.encoding.texture_codes` renders at inference), with
probability ``occlusion`` a random rectangle of the crop is cut from the mask
(the pipeline encodes occluded subjects from their visible pixels); the code
is sampled with the reparameterisation trick, decoded to keypoint features
and rendered at ``points`` in-mask pixels of the full view; the loss is
``colour_weight`` x colour MSE + ``kld_weight`` x KLD (NeTePu eq. 8). The
geometry model gets no gradient and no optimiser.

Cross-view training (``cross_view``, ours; 0 is NeTePu's autoencoder): with
this probability a sample's code is encoded from *another* view of the same
texture (another pose and camera) and rendered in the sample's view, so the
code must hold what is the same in every view -- the texture -- and nothing
of the view it was read from, which is what re-identification needs.

Contrastive codes (``contrast_weight`` > 0, ours): every sample also gets a
partner, another view (pose, camera) of its texture, encoded the same way, and
:func:`netepu.texture.losses.code_contrast_loss` of the two batches' codes is added
with that weight (the synthetic world's texture ids say which rows match).
``batch_sampling=textures`` fills each batch with as many different textures as
it can, so that look-alike textures meet in the contrastive loss.

Re-identification whitening (ours; ``reid_whitening_samples`` > 0): when
training ends, the codes of that many training samples (evenly spaced, no
occlusion) and their texture ids fit :func:`netepu.texture.embedding.within_class_whitening`
(shrinkage ``reid_shrinkage``; ``auto`` picks it by
:func:`netepu.texture.embedding.select_shrinkage` on two folds of training views; with the
model's ``reid_colour`` the codes carry the crops' colour statistics), stored in the
model before the final checkpoint
(:meth:`TextureTask.finish`); :func:`add_reid_whitening` adds it to a finished
checkpoint.

Evaluation: colour PSNR of the held-out sets and re-identification rank-1 /
mAP of the held-out codes' re-identification embeddings (:mod:`nsd.evaluation.reid`;
before the whitening is fitted, the codes themselves).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn

from netepu.geometry.model import GeometryModel, load_geometry_model
from netepu.texture.data import TextureData, _cache_root, build_texture_data, predicted_nnopcs_crops
from netepu.texture.embedding import select_shrinkage, within_class_whitening
from netepu.texture.evaluation import (
    evaluate_colour,
    heldout_codes,
    heldout_reid_inputs,
    synthesis_grid,
)
from netepu.texture.losses import code_contrast_loss, reparameterise, texture_loss
from netepu.texture.model import TextureModel, build_texture_model
from nsd.core.atomic import atomic_save_npz, atomic_save_torch
from nsd.core.config import ConfigSection
from nsd.core.device import move, on_cpu
from nsd.core.errors import ConfigError
from nsd.core.trainer import load_checkpoint
from nsd.evaluation.reid import reid_metrics

FALLBACK_SHRINKAGE = 0.01  # reid_shrinkage=auto when the training codes cannot choose

__all__ = [
    "TextureStageConfig",
    "TextureTask",
    "add_reid_whitening",
    "build_texture_stage",
    "load_texture_task",
]

log = logging.getLogger(__name__)

BATCH_SAMPLINGS = ("random", "textures")


@dataclass
class TextureStageConfig(ConfigSection):
    """``netepu.texture.optim`` (every field commented in the YAML file)."""

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml (netepu/texture)
    KEY: ClassVar[str] = "netepu.texture.optim"

    batch_size: int
    points: int
    lr: float
    weight_decay: float
    lr_decay: float
    lr_decay_every: int
    colour_weight: float
    kld_weight: float
    occlusion: float
    cross_view: float
    contrast_weight: float
    contrast_temperature: float
    batch_sampling: str
    eval_views: int
    reid_whitening_samples: int
    reid_shrinkage: float | str

    def validate(self) -> None:
        """Ranges and combinations (:meth:`from_config` and :meth:`defaults` call it)."""
        c = self
        if c.batch_size < 1 or c.points < 1 or not 0 <= c.occlusion <= 1:
            raise ConfigError("netepu.texture.optim: batch_size, points >= 1; occlusion in [0, 1]")
        if c.contrast_weight < 0 or c.contrast_temperature <= 0:
            raise ConfigError(
                "netepu.texture.optim: contrast_weight must be >= 0 and contrast_temperature > 0, "
                f"got {c.contrast_weight}, {c.contrast_temperature}"
            )
        auto = c.reid_shrinkage == "auto"
        if c.reid_whitening_samples < 0 or not (
            auto or (isinstance(c.reid_shrinkage, (int, float)) and c.reid_shrinkage >= 0)
        ):
            raise ConfigError(
                "netepu.texture.optim: reid_whitening_samples must be >= 0 and reid_shrinkage "
                f"a number >= 0 or 'auto', got {c.reid_whitening_samples}, {c.reid_shrinkage!r}"
            )
        if c.batch_sampling not in BATCH_SAMPLINGS:
            raise ConfigError(
                f"netepu.texture.optim.batch_sampling must be one of {BATCH_SAMPLINGS}, "
                f"got {c.batch_sampling!r}"
            )


def occlude(inside: Tensor, rng: np.random.Generator, prob: float) -> Tensor:
    """Cut a random axis-aligned rectangle (20-60 % of the side) from some crop masks.

    Args:
        inside: (B, S, S) bool.
        prob: probability per crop.

    Returns:
        (B, S, S) bool; a crop keeps at least a quarter of its pixels.
    """
    B, S, _ = inside.shape
    out = inside.clone()
    hit = rng.random(B) < prob
    for b in np.nonzero(hit)[0]:
        w, h = (rng.uniform(0.2, 0.6, 2) * S).astype(int)
        x, y = rng.integers(0, S - w + 1), rng.integers(0, S - h + 1)
        cut = out[b].clone()
        cut[y : y + h, x : x + w] = False
        if cut.sum() >= inside[b].sum() // 4:
            out[b] = cut
    return out


class TextureTask:
    """Texture model + frozen geometry + multi-texture data (see the module docstring)."""

    def __init__(
        self,
        texture: TextureModel,
        geometry: GeometryModel,
        data: TextureData,
        cfg: TextureStageConfig,
        nnopcs_train: np.ndarray,
        nnopcs_heldout: np.ndarray,
    ) -> None:
        self.texture, self.geometry, self.data, self.cfg = texture, geometry, data, cfg
        for p in geometry.parameters():
            p.requires_grad_(False)
        self.nnopcs_train, self.nnopcs_heldout = nnopcs_train, nnopcs_heldout
        tr = data.train
        st = tr["sample_texture"]
        self._by_texture = {int(t): np.nonzero(st == t)[0] for t in np.unique(st)}
        with torch.no_grad():  # the frozen geometry code of every training view
            geometry.eval()
            zs, fs = [], []
            kps = torch.from_numpy(tr["keypoints"])
            for s in range(0, len(kps), 256):
                code = geometry.encode(kps[s : s + 256])
                zs.append(code.z)
                fs.append(code.features)
            self.geo_z, self.geo_f = torch.cat(zs), torch.cat(fs)
        self.opt = torch.optim.AdamW(texture.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.sched = (
            {"texture": torch.optim.lr_scheduler.StepLR(self.opt, cfg.lr_decay_every, cfg.lr_decay)}
            if cfg.lr_decay_every > 0
            else {}
        )

    device = torch.device("cpu")  # where training steps run (:meth:`to`)

    def to(self, device: torch.device) -> TextureTask:
        """Train on ``device`` (evaluation, grids and the whitening fit stay on the CPU)."""
        self.device = device
        self.texture.to(device)
        self.geometry.to(device)
        self.geo_z, self.geo_f = self.geo_z.to(device), self.geo_f.to(device)
        return self

    def modules(self) -> dict[str, nn.Module]:
        return {"texture": self.texture, "geometry": self.geometry}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"texture": self.opt}

    def schedulers(self) -> dict[str, Any]:
        return self.sched

    def cross_view_sources(self, idx: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The samples the encoder reads: ``idx`` itself, or with probability ``cross_view``
        another sample of the same texture (another pose and camera)."""
        if self.cfg.cross_view <= 0:
            return idx
        src = idx.copy()
        chosen = rng.random(len(idx)) < self.cfg.cross_view
        src[chosen] = self.partners(idx[chosen], rng)
        return src

    def partners(self, idx: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Another sample of the same texture for each of ``idx`` (another pose and camera)."""
        pools = (self._by_texture[int(t)] for t in self.data.train["sample_texture"][idx])
        return np.array([pool[rng.integers(0, len(pool))] for pool in pools], dtype=idx.dtype)

    def encoder_input(
        self, src: np.ndarray, rng: np.random.Generator, occlusion: float | None = None
    ) -> Tensor:
        """Encoder input of training samples ``src``: masked RGB, (occluded) mask, NNOPCS;
        ``occlusion``: the occlusion probability (None: the config's)."""
        tr = self.data.train
        vs = tr["sample_view"][src]
        prob = self.cfg.occlusion if occlusion is None else occlusion
        inside = occlude(torch.from_numpy(tr["inside"][vs]), rng, prob)
        rgb = torch.from_numpy(tr["rgb"][src]).float() / 255 * inside[..., None]
        nn_ = torch.from_numpy(self.nnopcs_train[vs].astype(np.float32))
        return self.texture.encoder_input(rgb, inside, nn_)

    def batch_samples(self, rng: np.random.Generator) -> np.ndarray:
        """The training samples (B,) of one step.

        ``random``: uniform over all samples. ``textures``: the batch's textures are
        a random permutation of the pool (repeated when the batch is larger), each
        with a random sample, so that a batch holds as many different textures as
        it can -- every look-alike pair meets in every batch of >= T samples, where
        the contrastive loss must tell them apart (P x K batches of re-id training,
        with K views from the partners).
        """
        c, tr = self.cfg, self.data.train
        if c.batch_sampling == "random":
            return rng.integers(0, len(tr["sample_view"]), c.batch_size)
        pool = np.array(sorted(self._by_texture))
        reps = -(-c.batch_size // len(pool))
        textures = np.concatenate([rng.permutation(pool) for _ in range(reps)])[: c.batch_size]
        return np.array(
            [
                self._by_texture[int(t)][rng.integers(0, len(self._by_texture[int(t)]))]
                for t in textures
            ]
        )

    def batch(self, rng: np.random.Generator) -> dict[str, Any]:
        """Samples of one step: encoder input, render inputs and colour targets."""
        c, tr = self.cfg, self.data.train
        idx = self.batch_samples(rng)
        v = tr["sample_view"][idx]
        src = self.cross_view_sources(idx, rng)
        x = self.encoder_input(src, rng)
        pts = rng.integers(0, tr["pool_uv"].shape[1], (c.batch_size, c.points))
        vv = torch.from_numpy(v)
        cam = self.data.train_camera[torch.from_numpy(tr["camera"][v])]
        out = {
            "x": x,
            "view": vv,
            "keypoints": torch.from_numpy(tr["keypoints"][v]),
            "camera": cam,
            "uv": torch.from_numpy(tr["pool_uv"][v[:, None], pts].astype(np.float32)),
            "target": torch.from_numpy(tr["pool_colour"][idx[:, None], pts]).float() / 255,
        }
        if c.contrast_weight > 0:
            tex = tr["sample_texture"]
            partner = self.partners(src, rng)
            out["x_partner"] = self.encoder_input(partner, rng)
            out["same"] = torch.from_numpy(tex[src][:, None] == tex[partner][None])
        return out

    def training_step(self, step: int, rng: np.random.Generator) -> dict[str, Tensor]:
        b = move(self.batch(rng), self.device)
        mu, logvar = self.texture.encode(b["x"])
        noise = torch.from_numpy(rng.standard_normal(mu.shape).astype(np.float32)).to(mu)
        z = reparameterise(mu, logvar, noise)
        v = b["view"]
        ctx = self.texture.prepare(z, self.geo_z[v], self.geo_f[v], b["keypoints"], b["camera"])
        colour = self.texture.query(ctx, b["uv"])
        terms = texture_loss(
            colour, b["target"], mu, logvar, self.cfg.colour_weight, self.cfg.kld_weight
        )
        if self.cfg.contrast_weight > 0:
            partner, _ = self.texture.encode(b["x_partner"])
            terms["contrast"] = code_contrast_loss(
                mu, partner, b["same"], self.cfg.contrast_temperature
            )
            terms["loss"] = terms["loss"] + self.cfg.contrast_weight * terms["contrast"]
        return terms

    def codes(self) -> np.ndarray:
        """mu of every held-out crop and texture, (E, T, d_z)."""
        return heldout_codes(self.texture, self.data, self.nnopcs_heldout)

    def reid_inputs(self, codes: np.ndarray) -> np.ndarray:
        """What the re-identification whitening reads for the held-out codes (E, T, d_z):
        (E, T, reid_dims) (:meth:`netepu.texture.model.TextureModel.reid_input`)."""
        return heldout_reid_inputs(self.texture, self.data, self.nnopcs_heldout, codes)

    def reid_embeddings(self, inputs: np.ndarray) -> np.ndarray:
        """The model's re-identification embeddings of re-id inputs (..., reid_dims)."""
        flat = torch.from_numpy(inputs.reshape(-1, inputs.shape[-1]).astype(np.float64))
        with torch.no_grad():
            out = self.texture.whiten_reid(flat)
        return out.float().numpy().reshape(inputs.shape)

    def spaced_training_samples(self, n: int) -> np.ndarray:
        """Indices of ``n`` training samples evenly spaced over the set (all when fewer)."""
        total = len(self.data.train["sample_view"])
        return np.unique(np.linspace(0, total - 1, min(n, total)).round().astype(np.int64))

    @torch.no_grad()
    def training_reid_inputs(
        self, n: int, batch: int = 256
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Re-id inputs of ``n`` training samples evenly spaced (all when fewer), no
        occlusion: ((n, reid_dims), texture ids (n,), cameras (n,), views (n,))."""
        tr = self.data.train
        idx = self.spaced_training_samples(n)
        was = self.texture.training
        self.texture.eval()
        out = []
        unused = np.random.default_rng(0)  # occlusion 0: its draws change nothing
        for s in range(0, len(idx), batch):
            x = self.encoder_input(idx[s : s + batch], unused, occlusion=0.0)
            mu = self.texture.encode(x)[0]
            out.append(self.texture.reid_input(mu, *self.texture.crop_colours(x)))
        self.texture.train(was)
        views = tr["sample_view"][idx]
        return torch.cat(out).numpy(), tr["sample_texture"][idx], tr["camera"][views], views

    def fit_reid_whitening(self) -> dict[str, Any]:
        """Fit the re-identification whitening on training codes and store it in the model;
        returns the shrinkage used and, with ``auto``, the validation scores."""

        codes, ids, cams, views = self.training_reid_inputs(self.cfg.reid_whitening_samples)
        shrinkage, scores = self.cfg.reid_shrinkage, {}
        if shrinkage == "auto":  # two folds of views: the first and the second half
            try:
                shrinkage, scores = select_shrinkage(codes, ids, cams, views)
            except ValueError as e:
                log.warning("re-id shrinkage: %s; using %g", e, FALLBACK_SHRINKAGE)
                shrinkage = FALLBACK_SHRINKAGE
        mean, projection = within_class_whitening(codes, ids, float(shrinkage))
        self.texture.set_reid_whitening(mean, projection)
        log.info(
            "re-identification whitening fitted on %d training codes of %d textures "
            "(shrinkage %g%s)",
            len(codes),
            len(np.unique(ids)),
            shrinkage,
            f", validation {scores}" if scores else "",
        )
        return {"shrinkage": float(shrinkage), "validation": scores}

    def finish(self, step: int) -> None:
        """After the last step (before the final checkpoint): fit the whitening if enabled."""
        if self.cfg.reid_whitening_samples > 0:
            with on_cpu(self.texture, self.geometry):
                self.fit_reid_whitening()

    def evaluate(self, step: int) -> dict[str, float]:
        with on_cpu(self.texture, self.geometry):
            return self._evaluate()

    def _evaluate(self) -> dict[str, float]:
        codes = self.codes()
        out = evaluate_colour(
            self.texture, self.geometry, self.data, codes, max_views=self.cfg.eval_views
        )
        h = self.data.heldout
        E, T = codes.shape[:2]
        ids = np.tile(np.arange(T), E)
        cams = np.repeat(h["camera"], T)
        emb = self.reid_embeddings(self.reid_inputs(codes)).reshape(E * T, -1)
        out.update({f"reid/{k}": v for k, v in reid_metrics(emb, ids, cams).items()})
        return out

    def image_grids(self, step: int) -> dict[str, np.ndarray]:
        with on_cpu(self.texture, self.geometry):
            codes = self.codes()
            return self._grids(codes)

    def _grids(self, codes: np.ndarray) -> dict[str, np.ndarray]:
        return {
            f"texture_{'heldout_cameras' if held else 'heldout_poses'}": synthesis_grid(
                self.texture,
                self.geometry,
                self.data,
                codes,
                held,
                textures=list(range(min(6, codes.shape[1]))),
            )
            for held in (False, True)
        }


def _weights_key(path: str | Path) -> str:
    p = Path(path)
    st = p.stat()
    return hashlib.sha1(f"{p.resolve()}:{st.st_size}:{st.st_mtime_ns}".encode()).hexdigest()[:12]


def build_texture_stage(cfg: DictConfig) -> tuple[TextureTask, dict[str, Any]]:
    """The texture task of ``cfg`` (``init_from`` must name the geometry checkpoint)."""

    if not cfg.get("init_from"):
        raise ConfigError(
            "stage=texture needs init_from=<geometry checkpoint> (the frozen "
            "geometry model and its data)"
        )
    path = Path(cfg.init_from)
    if not path.is_file():
        raise ConfigError(f"init_from: geometry checkpoint {path} does not exist")
    geometry, geo_config = load_geometry_model(path)
    tex = OmegaConf.to_container(cfg.netepu.texture, resolve=True)
    try:
        model_cfg, data_cfg, optim = tex["model"], tex["data"], tex["optim"]
    except KeyError as e:
        raise ConfigError(f"netepu.texture lacks the section {e} (model, data, optim)") from e
    texture = build_texture_model(model_cfg, geometry)
    geo_data = dict(geo_config["netepu"]["data"])
    data = build_texture_data(
        data_cfg, geo_data, texture.cfg.crop_size, texture.cfg.crop_margin, progress=log.info
    )
    nn_train, nn_held = _surface_crops(geometry, texture, data, path)
    task = TextureTask(
        texture, geometry, data, TextureStageConfig.from_config(optim), nn_train, nn_held
    )
    # the run's netepu.model / netepu.data become the geometry checkpoint's (netepu.cli.train.run)
    found = {"model": geo_config["netepu"]["model"], **geo_data}
    return task, found


def _surface_crops(geometry, texture, data, weights: Path) -> tuple[np.ndarray, np.ndarray]:
    """The frozen geometry's NNOPCS (and normal) crops of the training and held-out views,
    cached next to the data under a key of the geometry weights and the crops."""
    cache = Path(data.config.cache_dir or "") if data.config.cache_dir else None
    root = cache or _cache_root(data.config)
    key = hashlib.sha1(  # the crops' size is part of the key: windows alone do not fix it
        f"{_weights_key(weights)}:{data.train['window'].sum():.6f}:"
        f"{len(data.train['window'])}:{len(data.heldout['window'])}:"
        f"{data.train['inside'].shape[1:]}".encode()
    ).hexdigest()[:12]
    normals = texture.cfg.use_normals
    key += "-normals" if normals else ""
    nn_path = root / f"texture-nnopcs-{key}.npz"
    if nn_path.is_file():
        with np.load(nn_path) as z:
            return z["train"], z["heldout"]
    tr, h = data.train, data.heldout
    cams = data.train_camera[torch.from_numpy(tr["camera"])]
    nn_train = predicted_nnopcs_crops(
        geometry,
        tr["keypoints"],
        cams,
        tr["window"],
        tr["inside"],
        progress=log.info,
        normals=normals,
    )
    nn_held = predicted_nnopcs_crops(
        geometry,
        h["keypoints"],
        data.heldout_camera_tensors(np.arange(len(h["pose"]))),
        h["window"],
        h["inside"],
        normals=normals,
    )
    atomic_save_npz(nn_path, train=nn_train, heldout=nn_held)
    return nn_train, nn_held


def load_texture_task(
    checkpoint: str | Path, first_texture: int | None = None
) -> tuple[TextureTask, dict[str, Any]]:
    """A finished run's texture task (its data and predicted NNOPCS crops, cached) with the
    trained weights, in eval mode, and the checkpoint's state. ``first_texture``: the data
    shows as many textures as the model was trained on, with consecutive ids from this one
    (e.g. generated textures it never saw) in the same poses and cameras (the data's random
    draws do not depend on the ids)."""

    state = load_checkpoint(checkpoint)
    cfg = OmegaConf.create(state["config"])
    if first_texture is not None:
        n = len(cfg.netepu.texture.data.textures)
        cfg.netepu.texture.data.textures = list(range(first_texture, first_texture + n))
    task, _ = build_texture_stage(cfg)
    task.texture.load_state_dict(state["modules"]["texture"])
    task.texture.eval()
    return task, state


def add_reid_whitening(
    checkpoint: str | Path, samples: int, shrinkage: float | str, colour: bool | None = None
) -> dict[str, Any]:
    """Fit the re-identification whitening into a finished texture checkpoint (in place,
    atomically); everything else in the checkpoint is kept. ``colour``: switch the
    model's ``reid_colour`` (None: keep it). Returns the fit's summary."""

    if samples < 1:
        raise ConfigError(f"add_reid_whitening: samples must be >= 1, got {samples}")
    state = load_checkpoint(checkpoint)
    cfg = OmegaConf.create(state["config"])
    cfg.netepu.texture.optim.reid_whitening_samples = samples
    cfg.netepu.texture.optim.reid_shrinkage = shrinkage
    if colour is not None:
        cfg.netepu.texture.model.reid_colour = bool(colour)
    TextureStageConfig.from_config(cfg.netepu.texture.optim)  # checked before any work
    task, _ = build_texture_stage(cfg)
    weights = {k: v for k, v in state["modules"]["texture"].items() if not k.startswith("reid_")}
    task.texture.load_state_dict(weights)  # the whitening is refitted: its old buffers go
    fit = task.fit_reid_whitening()
    state["modules"]["texture"] = task.texture.state_dict()
    state["config"] = OmegaConf.to_container(cfg, resolve=True)
    atomic_save_torch(state, Path(checkpoint))
    return {"samples": samples, "colour": bool(task.texture.cfg.reid_colour), **fit}
