r"""NePuMoo-like training and evaluation data for the geometry pipeline, from the synthetic world.

One individual of one species (default: the cow-like quadruped with its mean
body, like NePuMoo's single cow shape) is rendered by :mod:`nsd.synth` in
many sampled poses (random gait phase, gestures, heading and a small ground
offset) from a camera rig (default: NePuMoo's 3 rings of 8 cameras).

Training supervision (:class:`PointPools`)
    Every training view keeps a pool of supervision points drawn once with
    :mod:`netepu.geometry.sampling`: near-boundary and far silhouette points with their
    labels and in-mask points with their depth and NNOPCS. A training step
    draws its 750 + 750 + 500 points from the pools (:func:`sample_batch`);
    pools of twice that size keep the variety of fresh sampling at a tenth of
    the memory of full maps (350 MB instead of 3.5 GB for 640 poses x 24 views at
    256 x 192).

Evaluation (:class:`ViewSet`)
    Full ground-truth maps of held-out poses seen by training cameras
    (``heldout_poses``), of held-out poses seen by held-out cameras
    (``heldout_cameras``: other azimuths, heights and distances than any
    training camera) and of training poses and cameras (``train``).

Everything is cached under ``<NSD_CACHE or ~/.cache/nsd>/netepu/`` keyed by a
hash of the data config, and rebuilt when the config changes.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from netepu.geometry.maps import candidate_region
from netepu.geometry.renderer import view_frame
from netepu.geometry.sampling import sample_foreground_points, sample_silhouette_points
from nsd.cameras.batch import CameraBatch
from nsd.cameras.calibration import CameraRig
from nsd.core.atomic import atomic_save_npz
from nsd.core.config import ConfigSection
from nsd.core.errors import ConfigError
from nsd.synth import make_individual, make_rig, render_views, sample_pose
from nsd.synth.raycast import camera_rays
from nsd.synth.scene import default_cache_root

__all__ = [
    "DataConfig",
    "GeometryData",
    "PointPools",
    "ViewSet",
    "build_geometry_data",
    "make_point_pools",
    "render_new_poses",
    "sample_batch",
]

DATA_FORMAT = "netepu-geometry-data-v1"  # bump when the cached arrays change meaning


@dataclass
class DataConfig(ConfigSection):
    """The ``netepu/data`` config group (every field documented in the YAML files)."""

    APP: ClassVar[str] = "netepu_train"  # defaults: conf/netepu_train.yaml, section `netepu.data`
    KEY: ClassVar[str] = "netepu.data"

    species: str
    identity: int
    proportion_variation: float
    radius: float
    image_size: tuple[int, int]
    train_poses: int
    eval_poses: int
    eval_views_per_pose: int
    pose_variation: float
    position_jitter: float
    rig: dict
    heldout_rig: dict
    pool_near: int
    pool_far: int
    pool_foreground: int
    sigma_near: float
    margin: float
    seed: int
    cache_dir: str | None
    n_keypoints: int | None  # filled in from the species

    def __post_init__(self) -> None:
        self.image_size = tuple(int(v) for v in self.image_size)

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> DataConfig:
        """From a ``netepu.data`` mapping; keys it lacks take the shipped defaults."""
        return cls.defaults(**dict(cfg))

    def key(self) -> str:
        """Hash of everything that changes the data (not the cache folder)."""
        d = asdict(self)
        d.pop("cache_dir")
        d.pop("n_keypoints")
        d["format"] = DATA_FORMAT
        return hashlib.sha1(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:12]


@dataclass
class ViewSet:
    """Full ground-truth maps of n views (one individual each).

    Attributes:
        keypoints: world keypoints, (n, K, 3) float32.
        camera: ``K, R, t, dist`` with batch n (float32).
        mask: silhouettes, (n, H, W) bool.
        depth: camera depth Z, (n, H, W) float32 (0 on background).
        nnopcs: (n, H, W, 3) float16 in [0, 1] (0 on background).
    """

    keypoints: Tensor
    camera: CameraBatch
    mask: Tensor
    depth: Tensor
    nnopcs: Tensor

    def __len__(self) -> int:
        return self.keypoints.shape[0]

    @property
    def size(self) -> tuple[int, int]:
        return self.mask.shape[2], self.mask.shape[1]

    def subset(self, idx: list[int] | Tensor) -> ViewSet:
        idx = torch.as_tensor(idx, dtype=torch.int64)
        return ViewSet(self.keypoints[idx], self.camera[idx],
                       self.mask[idx], self.depth[idx], self.nnopcs[idx])


@dataclass
class PointPools:
    """Supervision points of V training views (see the module docstring).

    Attributes:
        pose: pose index of every view, (V,) int64.
        camera: camera index of every view, (V,) int64.
        near_uv, far_uv: silhouette points, (V, S_near|S_far, 2) int16 pixel centres (x, y).
        near_label, far_label: their labels, (V, S_.) bool.
        fg_uv: in-mask points, (V, F, 2) int16.
        fg_depth: their camera depth Z, (V, F) float32.
        fg_nnopcs: their NNOPCS, (V, F, 3) float16.
    """

    pose: np.ndarray
    camera: np.ndarray
    near_uv: np.ndarray
    near_label: np.ndarray
    far_uv: np.ndarray
    far_label: np.ndarray
    fg_uv: np.ndarray
    fg_depth: np.ndarray
    fg_nnopcs: np.ndarray

    def __len__(self) -> int:
        return len(self.pose)

    @staticmethod
    def concat(parts: list[PointPools]) -> PointPools:
        return PointPools(*(np.concatenate([getattr(p, f.name) for p in parts])
                            for f in fields(PointPools)))


@dataclass
class GeometryData:
    """Everything the geometry task trains and evaluates on.

    Attributes:
        config: the data config (``n_keypoints`` filled in).
        keypoints: training poses' world keypoints, (P, K, 3) float32.
        rig: training cameras.
        pools: supervision points of the training views.
        evaluation: named :class:`ViewSet` s.
    """

    config: DataConfig
    keypoints: Tensor
    rig: CameraRig
    pools: PointPools
    evaluation: dict[str, ViewSet]

    @property
    def camera(self) -> CameraBatch:
        """Training cameras as stacked tensors (C, ...)."""
        return self.rig.stacked(torch.float32)


def make_point_pools(
    keypoints: Tensor,
    camera: CameraBatch,
    mask: np.ndarray,
    depth: np.ndarray,
    nnopcs: np.ndarray,
    pose: np.ndarray,
    camera_index: np.ndarray,
    cfg: DataConfig,
    rng: np.random.Generator,
) -> PointPools:
    """Pools of supervision points of n views from their full maps.

    Args:
        keypoints: world keypoints of each view, (n, K, 3).
        camera: per-view camera tensors (batch n).
        mask: (n, H, W) bool; depth: (n, H, W); nnopcs: (n, H, W, 3).
        pose, camera_index: (n,) indices recorded in the pools.
        cfg: pool sizes, ``sigma_near``, ``margin``, ``radius``.
        rng: random generator.
    """
    n, h, w = mask.shape
    frame = view_frame(keypoints.double(), CameraBatch.from_mapping(camera).to(torch.float64),
                       cfg.radius)
    out: dict[str, list] = {f.name: [] for f in fields(PointPools)}
    for i in range(n):
        if not mask[i].any():
            raise ConfigError(f"view {i} (pose {pose[i]}, camera {camera_index[i]}) shows no "
                              "foreground; move the rig's target or the individual into view")
        region = candidate_region(frame.uv[i], float(frame.scale[i]), cfg.margin, (w, h))
        uv, label = sample_silhouette_points(mask[i], cfg.pool_near, cfg.pool_far, rng,
                                             cfg.sigma_near, region)
        fg = sample_foreground_points(mask[i], cfg.pool_foreground, rng).astype(np.int64)
        out["near_uv"].append(uv[: cfg.pool_near])
        out["near_label"].append(label[: cfg.pool_near] > 0.5)
        out["far_uv"].append(uv[cfg.pool_near:])
        out["far_label"].append(label[cfg.pool_near:] > 0.5)
        out["fg_uv"].append(fg)
        out["fg_depth"].append(depth[i][fg[:, 1], fg[:, 0]])
        out["fg_nnopcs"].append(nnopcs[i][fg[:, 1], fg[:, 0]])
    dtypes = {"near_uv": np.int16, "far_uv": np.int16, "fg_uv": np.int16,
              "fg_depth": np.float32, "fg_nnopcs": np.float16}
    arrays = {k: np.stack(v).astype(dtypes.get(k, bool)) for k, v in out.items()
              if k not in ("pose", "camera")}
    return PointPools(pose=np.asarray(pose, np.int64), camera=np.asarray(camera_index, np.int64),
                      **arrays)


def sample_batch(
    data: GeometryData,
    rng: np.random.Generator,
    batch_size: int,
    n_near: int = 750,
    n_far: int = 750,
    n_foreground: int = 500,
) -> dict[str, Tensor]:
    """Draw a training batch: random views, and random points of their pools.

    Returns:
        ``keypoints`` (B, K, 3), ``camera`` (dict, batch B), ``sil_uv`` (B, S, 2),
        ``sil_label`` (B, S), ``fg_uv`` (B, F, 2), ``fg_depth`` (B, F),
        ``fg_nnopcs`` (B, F, 3); float32.
    """
    p = data.pools
    v = rng.integers(0, len(p), batch_size)
    rows = v[:, None]
    near = rng.integers(0, p.near_uv.shape[1], (batch_size, n_near))
    far = rng.integers(0, p.far_uv.shape[1], (batch_size, n_far))
    fg = rng.integers(0, p.fg_uv.shape[1], (batch_size, n_foreground))
    sil_uv = np.concatenate([p.near_uv[rows, near], p.far_uv[rows, far]], 1)
    sil_label = np.concatenate([p.near_label[rows, near], p.far_label[rows, far]], 1)
    cams = data.camera
    ci = torch.from_numpy(p.camera[v])

    def t(x: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(x)).float()

    return {
        "keypoints": data.keypoints[torch.from_numpy(p.pose[v])],
        "camera": cams[ci],
        "sil_uv": t(sil_uv),
        "sil_label": t(sil_label),
        "fg_uv": t(p.fg_uv[rows, fg]),
        "fg_depth": t(p.fg_depth[rows, fg]),
        "fg_nnopcs": t(p.fg_nnopcs[rows, fg]),
    }


# ------------------------------------------------------------------ synthetic world
def _render(individual, poses, rig, size) -> dict[str, np.ndarray]:
    """Render poses from every camera of ``rig``: arrays (n_poses, C, ...)."""

    rays = camera_rays(rig, size)
    out = {"mask": [], "depth": [], "nnopcs": [], "keypoints": []}
    for pose in poses:
        r = render_views([individual], [pose], rays, background=False)
        m = r["visible"][:, 0]
        out["mask"].append(m.numpy())
        out["depth"].append(torch.where(m, r["depth"], torch.zeros_like(r["depth"])).numpy())
        out["nnopcs"].append(r["nnopcs"].numpy().astype(np.float16))
        out["keypoints"].append(r["keypoints3d"][0].numpy().astype(np.float32))
    return {k: np.stack(v) for k, v in out.items()}


def _sample_poses(individual, n: int, cfg: DataConfig, rng: np.random.Generator) -> list:
    poses = []
    for _ in range(n):
        pos = rng.uniform(-cfg.position_jitter, cfg.position_jitter, 2)
        poses.append(sample_pose(individual, rng, cfg.pose_variation, position=tuple(pos)))
    return poses


def _make_rig(spec: Mapping[str, Any], size: tuple[int, int]) -> CameraRig:
    spec = dict(spec)
    kind = spec.pop("kind", "nepumoo")
    return make_rig(kind, size, **spec)


def _view_set(keypoints: np.ndarray, rig: CameraRig, maps: dict[str, np.ndarray],
              views: list[tuple[int, int]]) -> ViewSet:
    cams = rig.stacked(torch.float32)
    p = np.array([a for a, _ in views], np.int64)
    c = np.array([b for _, b in views], np.int64)
    return ViewSet(
        torch.from_numpy(keypoints[p]), cams[torch.from_numpy(c)],
        torch.from_numpy(maps["mask"][p, c]), torch.from_numpy(maps["depth"][p, c]),
        torch.from_numpy(maps["nnopcs"][p, c]),
    )


def _store(arrays: dict[str, Any], name: str, vs: ViewSet) -> None:
    for f in ("keypoints", "mask", "depth", "nnopcs"):
        arrays[f"{name}/{f}"] = getattr(vs, f).numpy()
    for k, v in vs.camera.as_dict().items():
        arrays[f"{name}/camera_{k}"] = v.numpy()


def _build(cfg: DataConfig, progress: Callable[[str], None]) -> dict[str, Any]:
    rng = np.random.default_rng(cfg.seed)
    ind = make_individual(cfg.species, identity=cfg.identity, seed=cfg.seed,
                          proportion_variation=cfg.proportion_variation)
    rig = _make_rig(cfg.rig, cfg.image_size)
    held = _make_rig(cfg.heldout_rig, cfg.image_size)
    cams = rig.stacked(torch.float32)
    C = len(rig)
    train_poses = _sample_poses(ind, cfg.train_poses, cfg, rng)
    pools, kps = [], []
    chunk = 20
    for start in range(0, cfg.train_poses, chunk):
        maps = _render(ind, train_poses[start:start + chunk], rig, cfg.image_size)
        P = maps["mask"].shape[0]
        pose_idx = np.repeat(np.arange(start, start + P), C)
        cam_idx = np.tile(np.arange(C), P)
        flat = {k: maps[k].reshape(P * C, *maps[k].shape[2:])
                for k in ("mask", "depth", "nnopcs")}
        kp = torch.from_numpy(maps["keypoints"]).repeat_interleave(C, 0)
        cam = cams[torch.from_numpy(cam_idx)]
        pools.append(make_point_pools(kp, cam, flat["mask"], flat["depth"], flat["nnopcs"],
                                      pose_idx, cam_idx, cfg, rng))
        kps.append(maps["keypoints"])
        progress(f"training poses {start + P}/{cfg.train_poses}")
    arrays: dict[str, Any] = {"keypoints": np.concatenate(kps),
                              "n_keypoints": np.array(ind.num_keypoints)}
    for name, value in asdict(PointPools.concat(pools)).items():
        arrays[f"pools/{name}"] = value
    # held-out poses from the training cameras and from held-out cameras
    eval_poses = _sample_poses(ind, cfg.eval_poses, cfg, rng)
    for name, r in (("heldout_poses", rig), ("heldout_cameras", held)):
        maps = _render(ind, eval_poses, r, cfg.image_size)
        k = min(cfg.eval_views_per_pose, len(r))
        views = [(p, int(c)) for p in range(cfg.eval_poses)
                 for c in rng.choice(len(r), k, replace=False)]
        _store(arrays, name, _view_set(maps["keypoints"], r, maps, views))
        progress(f"evaluation views '{name}': {len(views)}")
    # training views (pools keep no full maps: render the chosen ones again)
    n = min(cfg.eval_poses * cfg.eval_views_per_pose, 64)
    chosen = sorted(set(rng.integers(0, cfg.train_poses, n).tolist()))
    maps = _render(ind, [train_poses[p] for p in chosen], rig, cfg.image_size)
    views = [(i, int(rng.integers(0, C))) for i in range(len(chosen))]
    _store(arrays, "train", _view_set(maps["keypoints"], rig, maps, views))
    return arrays


def render_new_poses(
    cfg: DataConfig | Mapping[str, Any], n_poses: int, seed: int,
    rig: Mapping[str, Any] | None = None,
) -> tuple[dict[str, np.ndarray], CameraRig]:
    """Render ``n_poses`` fresh poses of the data's individual from every camera of a rig.

    Poses are drawn like the training poses but from ``seed`` (use a seed other
    than the data's for unseen poses).

    Args:
        cfg: the data config.
        n_poses: number of poses.
        seed: pose seed.
        rig: rig spec (default: the training rig).

    Returns:
        ``(maps, rig)``: ``keypoints`` (P, K, 3), ``mask`` (P, C, H, W), ``depth``,
        ``nnopcs``; and the rig.
    """

    if not isinstance(cfg, DataConfig):
        cfg = DataConfig.from_mapping(cfg)
    ind = make_individual(cfg.species, identity=cfg.identity, seed=cfg.seed,
                          proportion_variation=cfg.proportion_variation)
    r = _make_rig(rig or cfg.rig, cfg.image_size)
    poses = _sample_poses(ind, n_poses, cfg, np.random.default_rng(seed))
    return _render(ind, poses, r, cfg.image_size), r


def _cache_root(cfg: DataConfig) -> Path:
    if cfg.cache_dir:
        return Path(cfg.cache_dir)

    return default_cache_root() / "netepu"


def build_geometry_data(
    cfg: DataConfig | Mapping[str, Any], progress: Callable[[str], None] | None = None
) -> GeometryData:
    """Load the data of ``cfg`` from the cache, rendering it first when missing.

    Args:
        cfg: a :class:`DataConfig` or the ``netepu.data`` mapping.
        progress: called with a message after each rendered chunk.
    """

    if not isinstance(cfg, DataConfig):
        cfg = DataConfig.from_mapping(cfg)
    path = _cache_root(cfg) / f"geometry-{cfg.species}-{cfg.key()}.npz"
    if path.is_file():
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
    else:
        arrays = _build(cfg, progress or (lambda _msg: None))
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_save_npz(path, **arrays)
    cfg.n_keypoints = int(arrays["n_keypoints"])
    rig = _make_rig(cfg.rig, cfg.image_size)
    pools = PointPools(**{f.name: arrays[f"pools/{f.name}"] for f in fields(PointPools)})
    evaluation = {}
    for name in ("heldout_poses", "heldout_cameras", "train"):
        evaluation[name] = ViewSet(
            torch.from_numpy(arrays[f"{name}/keypoints"]),
            CameraBatch.from_mapping(
                {k: arrays[f"{name}/camera_{k}"] for k in ("K", "R", "t", "dist")}
            ),
            torch.from_numpy(arrays[f"{name}/mask"]), torch.from_numpy(arrays[f"{name}/depth"]),
            torch.from_numpy(arrays[f"{name}/nnopcs"]),
        )
    return GeometryData(cfg, torch.from_numpy(arrays["keypoints"]), rig, pools, evaluation)

