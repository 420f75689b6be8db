"""Write a synthetic scene folder with full ground truth; the built-in default scene.

:func:`build_world` turns a :class:`~nsd.synth.config.SceneConfig` into
cameras, individuals and their trajectories (everything in memory; frames are
rendered with :meth:`SyntheticWorld.render`). :func:`write_scene` writes the
footage in the layout of :mod:`nsd.io.footage` plus a ``gt/`` folder, atomically
(built under a temporary name and renamed: an interrupted run leaves no scene)::

    <scene>/calibration.toml
    <scene>/<cam>/000000.png ...          # or <cam>.mp4 with video: true
    <scene>/gt/scene.json                 # metadata, config, species, statistics
    <scene>/gt/coco.json                  # COCO instances + keypoints (RLE masks)
    <scene>/gt/keypoints3d.npz            # identity_<i>: (T, K, 3) world metres
    <scene>/gt/keypoints2d.npz            # identity_<i>_uv (T, V, K, 2), _visibility (T, V, K)
    <scene>/gt/poses.npz                  # identity_<i>_translation/heading/angles
    <scene>/gt/dense/<cam>/<frame>.npz    # depth, instance, part, NNOPCS, amodal masks
    <scene>/gt/dense/<cam>/background.npz # depth of the static backdrop
    <scene>/gt/background/<cam>.png       # the static backdrop image
    <scene>/gt/preview.png                # cameras x frames grid, masks and NNOPCS

Every file, field and unit is documented in ``datasets/synthetic.md``.
:func:`default_scene` writes the default scene (``conf/synth.yaml``) once into
a cache folder and returns its path; :func:`tiny_config` gives scenes small
enough for tests.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import OmegaConf

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import write_toml
from nsd.core.atomic import atomic_directory
from nsd.core.errors import ConfigError
from nsd.synth.body import Individual, Pose, make_individual
from nsd.synth.coco import CocoBuilder
from nsd.synth.config import CLI_KEYS, GENERATOR_VERSION, SceneConfig
from nsd.synth.groundtruth import save_dense
from nsd.synth.motion import Trajectory, simulate_motion
from nsd.synth.nnopcs import nnopcs_bounds
from nsd.synth.preview import preview_cell, preview_grid
from nsd.synth.raycast import ViewRays, camera_rays
from nsd.synth.render import render_views
from nsd.synth.rigs import rig_from_config
from nsd.synth.texture import LOOK_ALIKE_PAIRS, POOL_SIZE

__all__ = [
    "SyntheticWorld",
    "build_world",
    "default_cache_root",
    "default_config",
    "default_scene",
    "load_config",
    "tiny_config",
    "torch_threads",
    "write_scene",
]

RENDER_THREADS = 1  # torch threads while writing a scene (see write_scene)


@dataclass
class SyntheticWorld:
    """A scene in memory: cameras, individuals and their motion.

    Attributes:
        config: the settings.
        rig: the cameras (image size set).
        individuals: N individuals (index = identity id).
        trajectories: one per individual, T frames.
        rays: the cameras' rays (reused by every frame).
    """

    config: SceneConfig
    rig: CameraRig
    individuals: list[Individual]
    trajectories: list[Trajectory]
    rays: ViewRays

    @property
    def num_frames(self) -> int:
        return self.config.num_frames

    def poses(self, t: int) -> list[Pose]:
        """The individuals' poses at frame ``t``."""
        return [tr.pose_at(t) for tr in self.trajectories]

    def render(self, t: int) -> dict:
        """All cameras of frame ``t`` (:func:`~nsd.synth.render.render_views`)."""
        return render_views(
            self.individuals,
            self.poses(t),
            self.rays,
            backdrop=self.config.backdrop,
            light=self.config.light,
        )


def _choose_textures(n: int, rng: np.random.Generator) -> list[int]:
    """``n`` distinct pool ids, never both members of a look-alike pair."""
    partner = {a: b for a, b in LOOK_ALIKE_PAIRS} | {b: a for a, b in LOOK_ALIKE_PAIRS}
    chosen: list[int] = []
    for i in rng.permutation(POOL_SIZE).tolist():
        if partner.get(i) not in chosen:
            chosen.append(i)
        if len(chosen) == n:
            return chosen
    raise ConfigError(f"num_individuals: cannot pick {n} distinct textures; give texture_ids")


def build_world(config: SceneConfig) -> SyntheticWorld:
    """Cameras, individuals and trajectories of ``config`` (deterministic in its seed)."""
    rng = np.random.default_rng(config.seed)
    N = config.num_individuals
    textures = (
        list(config.texture_ids) if config.texture_ids is not None else _choose_textures(N, rng)
    )
    individuals = [
        make_individual(
            sp,
            identity=i,
            texture_id=textures[i],
            seed=config.seed,
            proportion_variation=config.proportion_variation,
        )
        for i, sp in enumerate(config.species_of_individuals)
    ]
    rig = rig_from_config(config.rig, tuple(config.image_size))
    for c in rig:
        if np.hypot(*c.center[:2]) >= config.backdrop.wall_radius:
            raise ConfigError(
                f"rig: camera '{c.name}' stands outside the backdrop wall "
                f"(backdrop.wall_radius = {config.backdrop.wall_radius} m)"
            )
    trajectories = simulate_motion(
        individuals,
        config.num_frames,
        config.fps,
        config.motion,
        np.random.default_rng([config.seed, 1]),
    )
    rays = camera_rays(rig, tuple(config.image_size), config.supersample)
    return SyntheticWorld(config, rays.cameras, individuals, trajectories, rays)


# ------------------------------------------------------------------ writing
def _to_uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).numpy()


def _write_png(path: Path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"cannot write {path}")


class _Footage:
    """Writes the camera images: PNG folders or mp4 videos."""

    def __init__(
        self, root: Path, names: list[str], size: tuple[int, int], fps: float, video: bool
    ):
        self.root, self.names, self.video = root, names, video
        self.writers = []
        if video:
            fourcc = cv2.VideoWriter_fourcc(*"mp4v")
            for n in names:
                w = cv2.VideoWriter(str(root / f"{n}.mp4"), fourcc, float(fps), tuple(size))
                if not w.isOpened():
                    raise OSError(f"OpenCV cannot write {root / f'{n}.mp4'} (no mp4v encoder)")
                self.writers.append(w)
        else:
            for n in names:
                (root / n).mkdir()

    def file_name(self, v: int, t: int) -> str:
        return f"{self.names[v]}.mp4" if self.video else f"{self.names[v]}/{t:06d}.png"

    def write(self, v: int, t: int, rgb: np.ndarray) -> None:
        if self.video:
            self.writers[v].write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        else:
            _write_png(self.root / self.file_name(v, t), rgb)

    def close(self) -> None:
        for w in self.writers:
            w.release()


def _pair_boxes_overlap(boxes: torch.Tensor) -> torch.Tensor:
    """Whether any two non-empty boxes (V, N, 4) of a camera intersect, (V,)."""
    x0, y0, x1, y1 = boxes.unbind(-1)
    ix = torch.minimum(x1[:, :, None], x1[:, None, :]) - torch.maximum(
        x0[:, :, None], x0[:, None, :]
    )
    iy = torch.minimum(y1[:, :, None], y1[:, None, :]) - torch.maximum(
        y0[:, :, None], y0[:, None, :]
    )
    N = boxes.shape[1]
    off = ~torch.eye(N, dtype=torch.bool)
    return ((ix > 0) & (iy > 0) & off).flatten(1).any(-1)


FILES_DOC = {
    "calibration.toml": "cameras: anipose TOML (K, distortion, Rodrigues world-to-camera "
    "rotation, translation in metres, size)",
    "<cam>/<frame:06d>.png": "RGB images, 8 bit, lossless (or <cam>.mp4 with video: true)",
    "gt/scene.json": "this file",
    "gt/coco.json": "COCO instances and keypoints, one image per camera-frame (nsd.synth.coco)",
    "gt/keypoints3d.npz": "identity_<i>: (T, K, 3) float64 world keypoints, metres",
    "gt/keypoints2d.npz": "identity_<i>_uv: (T, V, K, 2) float64 pixels; "
    "identity_<i>_visibility: (T, V, K) uint8 0/1/2",
    "gt/poses.npz": "identity_<i>_translation (T, 3) m, _heading (T,) rad, _angles (T, K, 3) rad",
    "gt/dense/<cam>/<frame:06d>.npz": "depth, instance, part, nnopcs, amodal "
    "(nsd.synth.groundtruth)",
    "gt/dense/<cam>/background.npz": "depth (H, W) float32: camera-space Z of the static "
    "backdrop, inf on the sky",
    "gt/background/<cam>.png": "the static backdrop alone (exact median background)",
    "gt/preview.png": "cameras x frames: masks, amodal outlines, keypoints and NNOPCS overlaid",
}


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Set torch's intra-op threads to ``n`` inside the block (None: leave them)."""
    if n is None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


def write_scene(
    config: SceneConfig,
    out: str | os.PathLike,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    render_threads: int | None = RENDER_THREADS,
) -> Path:
    """Render and write a scene folder (see the module docstring).

    Frames are rendered in the calling thread while a second thread encodes and
    writes the files of the previous frames (PNG and zlib release the GIL), so
    two cores are used even with ``render_threads=1``.

    Args:
        config: the scene settings.
        out: the scene folder to create.
        overwrite: replace an existing folder (else :class:`FileExistsError`).
        progress: called as ``progress(frames_done, num_frames)``.
        render_threads: torch intra-op threads while rendering, restored
            afterwards; None leaves torch's setting alone. 1 (the default) is
            robust on a shared machine: many small parallel ops slow down by
            orders of magnitude when another process occupies a core.

    Returns:
        ``out`` as a :class:`Path`.
    """
    out = Path(out)
    world = build_world(config)
    with atomic_directory(out, overwrite=overwrite) as tmp, torch_threads(render_threads):
        _write(world, tmp, progress)
    return out


class _Writer:
    """Runs file writes in one background thread, in order; re-raises their errors."""

    def __init__(self, max_pending: int = 16) -> None:
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="nsd-synth-writer")
        self.pending: deque[Future] = deque()
        self.max_pending = max_pending

    def submit(self, fn: Callable, *args) -> None:
        self.pending.append(self.pool.submit(fn, *args))
        while len(self.pending) > self.max_pending or (self.pending and self.pending[0].done()):
            self.pending.popleft().result()

    def finish(self) -> None:
        while self.pending:
            self.pending.popleft().result()

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


def _write(world: SyntheticWorld, root: Path, progress) -> None:
    cfg = world.config
    rig, inds, rays = world.rig, world.individuals, world.rays
    V, N, T = len(rig), len(inds), cfg.num_frames
    W, H = rays.size
    names = rig.names
    write_toml(rig, root / "calibration.toml")
    gt = root / "gt"
    (gt / "background").mkdir(parents=True)
    for n in names:
        (gt / "dense" / n).mkdir(parents=True)
    footage = _Footage(root, names, (W, H), cfg.fps, cfg.video)
    writer = _Writer()
    species = [i.species for i in inds]
    coco = CocoBuilder(
        species, info={"description": "nsd-synth scene", "version": GENERATOR_VERSION}
    )
    uv_all = [np.zeros((T, V, i.num_keypoints, 2)) for i in inds]
    vis_all = [np.zeros((T, V, i.num_keypoints), np.uint8) for i in inds]
    stats = {"amodal_overlap": 0, "box_overlap": 0, "all_visible": 0}
    occluded_fraction: list[float] = []
    pv_cams = list(range(min(cfg.preview.cameras, V)))
    pv_frames = sorted({round(float(x)) for x in np.linspace(0, T - 1, min(cfg.preview.frames, T))})
    cells: dict[tuple[int, int], np.ndarray] = {}
    try:
        for t in range(T):
            r = world.render(t)
            rgb = _to_uint8(r["rgb"])
            if t == 0:
                bg = _to_uint8(r["background"])
                bd = cfg.backdrop.cast(rays.origins[rays.flat()[0]], rays.flat()[1], cfg.light)
                zbg = bd.distance.view(V, *rays.directions.shape[1:3]) * rays.z_per_distance
                zbg = rays.centre_samples(zbg).numpy().astype(np.float32)
                for v, n in enumerate(names):
                    _write_png(gt / "background" / f"{n}.png", bg[v])
                    np.savez_compressed(gt / "dense" / n / "background.npz", depth=zbg[v])
            visible, amodal = r["visible"].numpy(), r["amodal"].numpy()
            depth = r["depth"].numpy()
            instance, part, nnopcs = r["instance"].numpy(), r["part"].numpy(), r["nnopcs"].numpy()
            boxes, amodal_boxes = r["boxes"].numpy(), r["amodal_boxes"].numpy()
            kp3 = [k.numpy() for k in r["keypoints3d"]]
            for n in range(N):
                uv_all[n][t] = r["keypoints2d"][n].numpy()
                vis_all[n][t] = r["keypoint_visibility"][n].numpy()
            stats["amodal_overlap"] += int((r["amodal"].sum(1) > 1).flatten(1).any(-1).sum())
            stats["box_overlap"] += int(_pair_boxes_overlap(r["boxes"]).sum())
            for v in range(V):
                writer.submit(footage.write, v, t, rgb[v])
                image_id = t * V + v + 1
                coco.add_image(image_id, footage.file_name(v, t), (W, H), names[v], t)
                root_depth = [float(rig[v].project(k[:1])[1][0]) for k in kp3]
                coco.add_instances(
                    image_id,
                    inds,
                    visible[v],
                    amodal[v],
                    boxes[v],
                    amodal_boxes[v],
                    depth[v],
                    [uv_all[n][t, v] for n in range(N)],
                    [vis_all[n][t, v] for n in range(N)],
                    root_depth,
                )
                va = visible[v].reshape(N, -1).sum(1)
                aa = amodal[v].reshape(N, -1).sum(1)
                stats["all_visible"] += int((va > 0).all())
                occluded_fraction += [1.0 - a / b for a, b in zip(va, aa, strict=True) if b > 0]
                if cfg.dense:
                    writer.submit(
                        save_dense, gt / "dense" / names[v] / f"{t:06d}.npz",
                        depth[v], instance[v], part[v], nnopcs[v], amodal[v],
                    )  # fmt: skip
                if v in pv_cams and t in pv_frames:
                    kps = [
                        np.concatenate([uv_all[n][t, v], vis_all[n][t, v, :, None]], axis=1)
                        for n in range(N)
                    ]
                    cells[(v, t)] = preview_cell(
                        rgb[v], instance[v], amodal[v], nnopcs[v], kps,
                        f"{names[v]} t={t}", cfg.preview.zoom,
                    )  # fmt: skip
            if progress is not None:
                progress(t + 1, T)
        writer.finish()
    finally:
        writer.close()
        footage.close()
    grid = preview_grid([[cells[(v, t)] for t in pv_frames] for v in pv_cams])
    _write_png(gt / "preview.png", grid)
    (gt / "coco.json").write_text(json.dumps(coco.to_json()))
    kp3d: dict[str, np.ndarray] = {}
    kp2: dict[str, np.ndarray] = {}
    poses: dict[str, np.ndarray] = {}
    for n, (ind, tr) in enumerate(zip(inds, world.trajectories, strict=True)):
        kp3d[f"identity_{ind.identity}"] = ind.keypoints3d(tr.poses).numpy()
        kp2[f"identity_{ind.identity}_uv"] = uv_all[n]
        kp2[f"identity_{ind.identity}_visibility"] = vis_all[n]
        poses[f"identity_{ind.identity}_translation"] = tr.poses.translation.numpy()
        poses[f"identity_{ind.identity}_heading"] = tr.poses.heading.numpy()
        poses[f"identity_{ind.identity}_angles"] = tr.poses.angles.numpy()
    np.savez_compressed(gt / "keypoints3d.npz", **kp3d)
    np.savez_compressed(gt / "keypoints2d.npz", **kp2)
    np.savez_compressed(gt / "poses.npz", **poses)
    frames = V * T
    statistics = {
        "camera_frames": frames,
        "amodal_overlap_fraction": stats["amodal_overlap"] / frames,
        "visible_box_overlap_fraction": stats["box_overlap"] / frames,
        "all_individuals_visible_fraction": stats["all_visible"] / frames,
        "mean_occluded_fraction": float(np.mean(occluded_fraction)) if occluded_fraction else 0.0,
        "annotations": len(coco.annotations),
        "fully_occluded_annotations": len(coco.occluded),
    }
    (gt / "scene.json").write_text(json.dumps(_metadata(world, statistics), indent=1))


def _metadata(world: SyntheticWorld, statistics: dict) -> dict[str, Any]:
    cfg = world.config
    sp = {i.species.name: i.species for i in world.individuals}
    return {
        "format": "nsd-synth",
        "generator_version": GENERATOR_VERSION,
        "config_hash": cfg.hash(),
        "seed": cfg.seed,
        "num_frames": cfg.num_frames,
        "fps": cfg.fps,
        "image_size": list(world.rays.size),
        "footage": "video" if cfg.video else "png",
        "units": {
            "world": "metres; right-handed, z up, ground plane z = 0",
            "angles": "radians",
            "depth": "camera-space Z in metres (OpenCV camera: looks along +z); inf on background",
            "pixels": "keypoints: (0, 0) is the centre of the top-left pixel; "
            "boxes: pixel edges, [x, y, w, h]",
            "nnopcs": "[0, 1]^3: neutral-pose coordinate on the species' mean body, "
            "normalised by nnopcs_bounds",
        },
        "cameras": [
            {
                "name": c.name,
                "size": list(c.size),
                "K": c.K.tolist(),
                "dist": c.dist.tolist(),
                "R": c.R.tolist(),
                "t": c.t.tolist(),
                "centre": c.center.tolist(),
            }
            for c in world.rig
        ],
        "species": {
            name: s.to_json() | {"nnopcs_bounds": nnopcs_bounds(s).to_json()}
            for name, s in sp.items()
        },
        "individuals": [i.to_json() | {"texture": i.texture.to_json()} for i in world.individuals],
        "look_alike_texture_pairs": [list(p) for p in LOOK_ALIKE_PAIRS],
        "statistics": statistics,
        "files": FILES_DOC,
        "config": cfg.to_dict(),
    }


# ------------------------------------------------------------------ configs and the default scene
def load_config(name: str = "synth", overrides: dict[str, Any] | None = None) -> SceneConfig:
    """The scene settings of a shipped Hydra config (``nsd.conf/<name>.yaml``).

    Args:
        name: config name.
        overrides: top-level values to change.
    """

    with (files("nsd.conf") / f"{name}.yaml").open() as f:
        values = OmegaConf.to_container(OmegaConf.load(f), resolve=True)
    values = {k: v for k, v in values.items() if k not in CLI_KEYS}
    return SceneConfig.from_dict({**values, **(overrides or {})})


def default_config() -> SceneConfig:
    """The default scene: ``conf/synth.yaml`` as shipped."""
    return load_config("synth")


def tiny_config(**changes: Any) -> SceneConfig:
    """A scene small enough for tests: 2 cameras x 6 frames at 48 x 48, 2 bipeds.

    Keyword arguments replace settings (e.g. ``num_individuals=3``).
    """
    values: dict[str, Any] = {
        "seed": 0,
        "num_frames": 6,
        "image_size": [48, 48],
        "num_individuals": 2,
        "species": ["biped"],
        "rig": {"kind": "ring", "count": 2, "radius": 4.0, "height": 2.0, "fov_deg": 50.0,
                "start_deg": 30.0},
        "motion": {"interaction": "close", "area_radius": 1.2},
        "preview": {"cameras": 2, "frames": 2, "zoom": 1},
    }  # fmt: skip
    values.update(changes)
    return SceneConfig.from_dict(values)


def default_cache_root() -> Path:
    """``$NSD_CACHE`` or ``~/.cache/nsd``."""
    return Path(os.environ.get("NSD_CACHE") or Path.home() / ".cache" / "nsd")


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def default_scene(
    cache_root: str | os.PathLike | None = None, config: SceneConfig | None = None
) -> Path:
    """The default scene's folder, written on first use and reused afterwards.

    The folder is ``<cache_root>/scenes/default-<config hash>`` with ``cache_root``
    defaulting to ``$NSD_CACHE`` or ``~/.cache/nsd``. Concurrent callers wait
    for each other (a file lock), and the scene is written atomically.

    Args:
        cache_root: where to keep it.
        config: another scene to cache the same way (default: :func:`default_config`).
    """
    config = config or default_config()
    root = Path(cache_root) if cache_root is not None else default_cache_root()
    path = root / "scenes" / f"default-{config.hash()}"
    if (path / "gt" / "scene.json").is_file():
        return path
    with _locked(root / "scenes" / f".default-{config.hash()}.lock"):
        if not (path / "gt" / "scene.json").is_file():
            write_scene(config, path, overwrite=True)
    return path
