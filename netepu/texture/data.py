r"""Multi-texture data for the texture stage, from the synthetic world (NePuMoo-like).

The individual, its body, rig and pose sampling are the geometry checkpoint's
(:class:`netepu.geometry.data.DataConfig`); what is added is *textures*: every view is
shown with several textures of the pool (``textures``; the default holds all
16 pool textures, among them the look-alike pairs
:data:`nsd.synth.LOOK_ALIKE_PAIRS`). A view's body geometry does not depend on
the texture, so each pose is ray-cast once (:func:`nsd.synth.render_views`,
black background as NeTePu's masked images) and its colours for any texture
are the texture looked up at the NNOPCS of the visible surface, shaded by
:func:`nsd.synth.shading.lambert` -- exactly what ``render_views`` computes
for an individual wearing that texture (tested).

Per training view (``V = train_poses x cameras``)
    world keypoints, camera index, the encoder's crop window and in-mask crop
    pixels (:func:`netepu.texture.encoding.encoder_crops`), the ground-truth NNOPCS crop
    and a pool of ``pool`` in-mask pixels; per (view, texture) *sample* the RGB
    crop (uint8) and the colours of the pool pixels.

Evaluation (``heldout``)
    ``eval_poses`` poses never used in training, seen by every camera of the
    training rig and of the held-out rig (other azimuths, heights, distances),
    with every texture: crops for re-identification and, for
    ``psnr_cameras`` cameras per pose and rig, full masks and colour images for
    the colour PSNR of held-out poses (training cameras) and held-out
    cameras.

Cached under ``<NSD_CACHE or ~/.cache/nsd>/netepu/`` keyed by a hash of both
configs.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from netepu.geometry.data import DataConfig
from netepu.geometry.sampling import sample_foreground_points
from netepu.texture.crops import crop_grid, crop_windows, sample_masked
from netepu.texture.encoding import predicted_surface
from nsd.cameras.batch import CameraBatch
from nsd.cameras.calibration import CameraRig
from nsd.core.atomic import atomic_save_npz
from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError
from nsd.synth import get_texture, make_individual, make_rig, render_views, sample_pose
from nsd.synth.raycast import camera_rays
from nsd.synth.render import DEFAULT_LIGHT
from nsd.synth.scene import default_cache_root
from nsd.synth.shading import lambert

__all__ = [
    "TextureData",
    "TextureDataConfig",
    "build_texture_data",
    "predicted_nnopcs_crops",
    "shade_texture",
]

TEXTURE_DATA_FORMAT = "netepu-texture-data-v1"


@dataclass
class TextureDataConfig(ConfigSection):
    """The ``netepu.texture.data`` config (every field commented in the YAML file)."""

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml (netepu/texture)
    KEY: ClassVar[str] = "netepu.texture.data"

    textures: list[int]
    train_poses: int
    textures_per_view: int
    eval_poses: int
    psnr_cameras: int
    pool: int
    seed: int
    cache_dir: str | None

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> TextureDataConfig:
        """From a ``netepu.texture.data`` mapping; keys it lacks take the shipped defaults."""
        return cls.defaults(**dict(cfg))

    def validate(self) -> None:
        self.textures = [int(t) for t in self.textures]
        if not self.textures or not 1 <= self.textures_per_view <= len(self.textures):
            raise ConfigError(
                "netepu.texture.data: need >= 1 texture and 1 <= textures_per_view <= len(textures)"
            )


@dataclass
class TextureData:
    """Arrays of the texture stage (see the module docstring); numpy, CPU.

    Attributes:
        textures: texture ids, (T,).
        train: ``keypoints`` (V, K, 3), ``camera`` (V,), ``window`` (V, 3),
            ``inside`` (V, S, S) bool, ``nnopcs`` (V, S, S, 3) f16 (ground truth),
            ``pool_uv`` (V, P, 2) int16, and per sample ``sample_view`` (N,),
            ``sample_texture`` (N,) (index into ``textures``), ``rgb`` (N, S, S, 3)
            uint8, ``pool_colour`` (N, P, 3) uint8.
        heldout: ``keypoints`` (E, K, 3), ``pose`` (E,), ``camera`` (E,) (index
            into the concatenated rigs), ``heldout_camera`` (E,) bool, ``cam_K``,
            ``cam_R``, ``cam_t``, ``cam_dist`` per view, ``window``, ``inside``,
            ``nnopcs``, ``rgb`` (E, T, S, S, 3) uint8, ``psnr_view`` (F,) indices of
            views with full maps, ``mask`` (F, H, W) bool, ``colour`` (F, T, H, W, 3) uint8.
        train_camera: training rig cameras, stacked tensors (C, ...).
    """

    config: TextureDataConfig
    geometry: DataConfig
    textures: np.ndarray
    train: dict[str, np.ndarray]
    heldout: dict[str, np.ndarray]
    train_camera: CameraBatch

    def heldout_camera_tensors(self, idx: np.ndarray) -> CameraBatch:
        return CameraBatch.from_mapping(
            {k: self.heldout[f"cam_{k}"][idx] for k in ("K", "R", "t", "dist")}
        )


def shade_texture(texture_id: int, nnopcs: Tensor, normal: Tensor) -> Tensor:
    """Shaded colour of a texture at visible surface points.

    Args:
        texture_id: pool (or generated) texture id.
        nnopcs: (N, 3) NNOPCS of the points; normal: (N, 3) unit world normals.

    Returns:
        (N, 3) colour in [0, 1] as :func:`nsd.synth.render_views` shades it.
    """

    return lambert(get_texture(texture_id)(nnopcs), normal, DEFAULT_LIGHT)


def _key(cfg: TextureDataConfig, geo: DataConfig, crop_size: int, margin: float | None) -> str:
    d = {k: v for k, v in asdict(cfg).items() if k != "cache_dir"}
    g = {
        k: v
        for k, v in asdict(geo).items()
        if k
        not in (
            "cache_dir",
            "n_keypoints",
            "pool_near",
            "pool_far",
            "pool_foreground",
            "sigma_near",
            "train_poses",
            "eval_poses",
            "eval_views_per_pose",
        )
    }
    d |= {"geometry": g, "crop_size": crop_size, "margin": margin, "format": TEXTURE_DATA_FORMAT}
    return hashlib.sha1(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _poses(ind, n: int, geo: DataConfig, rng: np.random.Generator) -> list:
    out = []
    for _ in range(n):
        pos = rng.uniform(-geo.position_jitter, geo.position_jitter, 2)
        out.append(sample_pose(ind, rng, geo.pose_variation, position=tuple(pos)))
    return out


def _rig(spec: Mapping[str, Any], size: tuple[int, int]):
    spec = dict(spec)
    return make_rig(spec.pop("kind", "nepumoo"), size, **spec)


def _crops(colour: Tensor, mask: Tensor, crop_size: int, margin: float | None):
    """Window, inside and crops of full images (n, H, W, C) with masks (n, H, W)."""
    window = crop_windows(mask, margin)
    grid = crop_grid(window, crop_size)
    crop, inside = sample_masked(colour, mask, grid)
    return window, inside, crop


def _render_pose(ind, pose, rays) -> dict[str, Tensor]:
    r = render_views([ind], [pose], rays, background=False)
    return {
        "mask": r["visible"][:, 0],
        "nnopcs": r["nnopcs"].float(),
        "normal": r["normal"].float(),
        "keypoints": r["keypoints3d"][0].float(),
    }


def _colours(tex_ids, r: dict[str, Tensor], views: list[int]) -> Tensor:
    """(len(views), len(tex_ids), H, W, 3) float colours of the views."""
    m = r["mask"][views]
    nn, nm = r["nnopcs"][views][m], r["normal"][views][m]
    out = torch.zeros(len(views), len(tex_ids), *m.shape[1:], 3)
    for j, t in enumerate(tex_ids):
        out[:, j][m] = shade_texture(int(t), nn, nm)
    return out


def _to_u8(x: Tensor) -> np.ndarray:
    return (x.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


@dataclass
class _World:
    """What both the training and the held-out renders of :func:`_build` share."""

    cfg: TextureDataConfig
    geo: DataConfig
    individual: Any
    textures: np.ndarray  # (T,) pool ids
    crop_size: int
    margin: float | None
    rng: np.random.Generator
    progress: Callable[[str], None]


def _build(
    cfg: TextureDataConfig,
    geo: DataConfig,
    crop_size: int,
    margin: float | None,
    progress: Callable[[str], None],
) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(cfg.seed)
    ind = make_individual(
        geo.species,
        identity=geo.identity,
        seed=geo.seed,
        proportion_variation=geo.proportion_variation,
    )
    rig = _rig(geo.rig, geo.image_size)
    held = _rig(geo.heldout_rig, geo.image_size)
    world = _World(cfg, geo, ind, np.asarray(cfg.textures), crop_size, margin, rng, progress)
    out = _training_views(world, rig)
    out.update(_heldout_views(world, rig, held))
    out["textures"] = world.textures
    return out


def _stacked(lists: dict[str, list], prefix: str) -> dict[str, np.ndarray]:
    return {
        f"{prefix}/{k}": np.stack(v) if isinstance(v[0], np.ndarray) else np.asarray(v)
        for k, v in lists.items()
    }


def _texture_choices(w: _World, n_views: int, state: list) -> list[list[int]]:
    """``textures_per_view`` distinct textures for each of ``n_views`` views, cycling through
    permutations of the pool so that every texture is shown equally often.
    ``state`` = [order, cursor] carries the cycle from pose to pose."""
    T = len(w.textures)
    chosen = []
    for _ in range(n_views):
        pick: list[int] = []
        while len(pick) < w.cfg.textures_per_view:
            if state[1] == T:
                state[0], state[1] = w.rng.permutation(T), 0
            if state[0][state[1]] not in pick:
                pick.append(int(state[0][state[1]]))
            state[1] += 1
        chosen.append(pick)
    return chosen


_TRAIN_KEYS = ("keypoints", "camera", "window", "inside", "nnopcs", "pool_uv", "sample_view",
               "sample_texture", "rgb", "pool_colour")  # fmt: skip


def _training_views(w: _World, rig: CameraRig) -> dict[str, np.ndarray]:
    """Training poses from every camera of ``rig``, each view with a few textures."""
    cfg = w.cfg
    rays = camera_rays(rig, w.geo.image_size)
    C = len(rig)
    tr: dict[str, list] = {k: [] for k in _TRAIN_KEYS}
    state = [w.rng.permutation(len(w.textures)), 0]
    V = 0
    for p, pose in enumerate(_poses(w.individual, cfg.train_poses, w.geo, w.rng)):
        r = _render_pose(w.individual, pose, rays)
        views = [c for c in range(C) if r["mask"][c].any()]
        chosen = _texture_choices(w, len(views), state)
        mask = r["mask"][views]
        window, inside, nn_crop = _crops(r["nnopcs"][views], mask, w.crop_size, w.margin)
        for i, c in enumerate(views):
            uv = sample_foreground_points(mask[i].numpy(), cfg.pool, w.rng).astype(np.int64)
            tr["keypoints"].append(r["keypoints"].numpy())
            tr["camera"].append(c)
            tr["window"].append(window[i].numpy())
            tr["inside"].append(inside[i].numpy())
            tr["nnopcs"].append(nn_crop[i].numpy().astype(np.float16))
            tr["pool_uv"].append(uv.astype(np.int16))
            col = _colours(w.textures[chosen[i]], r, [c])[0]  # (textures_per_view, H, W, 3)
            one = mask[i : i + 1].expand(len(col), -1, -1)
            _, _, rgb = _crops(col, one, w.crop_size, w.margin)
            for j, t in enumerate(chosen[i]):
                tr["sample_view"].append(V)
                tr["sample_texture"].append(t)
                tr["rgb"].append(_to_u8(rgb[j]))
                tr["pool_colour"].append(_to_u8(col[j][uv[:, 1], uv[:, 0]]))
            V += 1
        if (p + 1) % 20 == 0:
            w.progress(f"texture data: training poses {p + 1}/{cfg.train_poses}")
    return _stacked(tr, "train")


_HELDOUT_KEYS = ("keypoints", "pose", "camera", "heldout_camera", "window", "inside", "nnopcs",
                 "rgb", "mask", "colour", "psnr_view")  # fmt: skip


def _heldout_views(w: _World, rig: CameraRig, held: CameraRig) -> dict[str, np.ndarray]:
    """Held-out poses, seen by every camera of both rigs, with every texture."""
    cfg, T, C = w.cfg, len(w.textures), len(rig)
    ev: dict[str, list] = {k: [] for k in _HELDOUT_KEYS}
    cams = CameraBatch.cat([rig.stacked(torch.float32), held.stacked(torch.float32)])
    rays, held_rays = camera_rays(rig, w.geo.image_size), camera_rays(held, w.geo.image_size)
    E = 0
    for p, pose in enumerate(_poses(w.individual, cfg.eval_poses, w.geo, w.rng)):
        for offset, rr in ((0, rays), (C, held_rays)):
            r = _render_pose(w.individual, pose, rr)
            views = [c for c in range(r["mask"].shape[0]) if r["mask"][c].any()]
            col = _colours(w.textures, r, views)
            mask = r["mask"][views]
            window, inside, nn_crop = _crops(r["nnopcs"][views], mask, w.crop_size, w.margin)
            n_psnr = min(cfg.psnr_cameras, len(views))
            psnr = set(w.rng.choice(len(views), n_psnr, replace=False).tolist())
            for i, c in enumerate(views):
                one = mask[i : i + 1].expand(T, -1, -1)
                rgb = _crops(col[i], one, w.crop_size, w.margin)[2]
                ev["keypoints"].append(r["keypoints"].numpy())
                ev["pose"].append(p)
                ev["camera"].append(offset + c)
                ev["heldout_camera"].append(offset > 0)
                ev["window"].append(window[i].numpy())
                ev["inside"].append(inside[i].numpy())
                ev["nnopcs"].append(nn_crop[i].numpy().astype(np.float16))
                ev["rgb"].append(_to_u8(rgb))
                if i in psnr:
                    ev["psnr_view"].append(E)
                    ev["mask"].append(mask[i].numpy())
                    ev["colour"].append(_to_u8(col[i]))
                E += 1
        w.progress(f"texture data: held-out poses {p + 1}/{cfg.eval_poses}")
    out = _stacked(ev, "heldout")
    camera_index = out["heldout/camera"]
    for k, v in cams.as_dict().items():
        out[f"heldout/cam_{k}"] = v.numpy()[camera_index]
    return out


def _cache_root(cfg: TextureDataConfig) -> Path:
    if cfg.cache_dir:
        return Path(cfg.cache_dir)

    return default_cache_root() / "netepu"


def build_texture_data(
    cfg: TextureDataConfig | Mapping[str, Any],
    geometry: DataConfig | Mapping[str, Any],
    crop_size: int,
    margin: float | None,
    progress: Callable[[str], None] | None = None,
) -> TextureData:
    """Load the texture data from the cache, rendering it first when missing.

    Args:
        cfg: the texture data config.
        geometry: the geometry checkpoint's data config (species, rigs, poses).
        crop_size, margin: the encoder's crop (:class:`netepu.texture.config.TextureConfig`).
        progress: called with a message now and then.
    """

    if not isinstance(cfg, TextureDataConfig):
        cfg = TextureDataConfig.from_mapping(cfg)
    if not isinstance(geometry, DataConfig):
        geometry = DataConfig.from_mapping(
            {k: v for k, v in dict(geometry).items() if k != "n_keypoints"}
        )
    path = _cache_root(cfg) / (
        f"texture-{geometry.species}-{_key(cfg, geometry, crop_size, margin)}.npz"
    )
    if path.is_file():
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
    else:
        arrays = _build(cfg, geometry, crop_size, margin, progress or (lambda _m: None))
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_save_npz(path, **arrays)
    rig = _rig(geometry.rig, geometry.image_size)
    split = {"train": {}, "heldout": {}}
    for k, v in arrays.items():
        if "/" in k:
            a, b = k.split("/", 1)
            split[a][b] = v
    return TextureData(
        cfg,
        geometry,
        arrays["textures"],
        split["train"],
        split["heldout"],
        rig.stacked(torch.float32),
    )


@torch.no_grad()
def predicted_nnopcs_crops(
    geometry,
    keypoints: np.ndarray,
    camera: Mapping[str, Tensor],
    window: np.ndarray,
    inside: np.ndarray,
    batch: int = 64,
    progress: Callable[[str], None] | None = None,
    normals: bool = False,
) -> np.ndarray:
    """NNOPCS crops rendered by the frozen geometry model at the in-mask crop pixels.

    What the encoder sees in training and at inference
    (:func:`netepu.texture.encoding.texture_codes` renders the same pixels).

    Args:
        geometry: the :class:`netepu.geometry.model.GeometryModel`.
        keypoints: (n, K, 3) world keypoints.
        camera: per-view camera tensors (batch n).
        window: (n, 3) crop windows; inside: (n, S, S) bool in-mask crop pixels.
        normals: append the world normals of the rendered depth
            (:func:`netepu.texture.encoding.predicted_surface`).

    Returns:
        (n, S, S, 3) or (n, S, S, 6) float16, zeros outside.
    """

    geometry.eval()
    n, S = inside.shape[:2]
    out = np.zeros((n, S, S, 6 if normals else 3), np.float16)
    for s in range(0, n, batch):
        sl = slice(s, min(n, s + batch))
        uv = crop_grid(torch.from_numpy(window[sl]).double(), S).float()
        keep = torch.from_numpy(inside[sl])
        kps = torch.from_numpy(keypoints[sl]).float()
        cam = camera[sl].to(torch.float32)
        out[sl] = predicted_surface(geometry, kps, cam, uv, keep, normals).numpy()
        if progress and (s // batch) % 10 == 0:
            progress(f"predicted NNOPCS crops {min(n, s + batch)}/{n}")
    return out
