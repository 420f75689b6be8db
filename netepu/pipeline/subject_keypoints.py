r"""Label-free 3D keypoints of exported subjects: inverse rendering of their multi-view masks.

For each selected frame of an ``nsd-export`` folder, the visible masks of one
subject (one cross-view ``subject_id``) in every camera that shows it go into
:func:`netepu.geometry.inverse.invert_silhouettes` with a trained NeTePu geometry model
and the scene's calibration; the recovered world keypoints are written for
every annotation (camera-frame row) of that subject in that frame, in the
``keypoints3d.npz`` format ``netepu-embed`` reads (:mod:`nsd.io.keypoints`;
``subject_loss`` is the inversion's final silhouette loss).

Visible masks of an occluded subject are partial. With ``occlusion`` on, the other
subjects' visible masks of the same camera-frame are the inversion's occluders: the
render is not penalised where another subject covers the image, only where the
background is seen (:func:`netepu.geometry.inverse.invert_silhouettes`).

A cold start refines the prediction of a learned initialiser (``initialiser``: the shipped one
of the species in ``nsd-run``, :mod:`netepu.geometry.initialiser`) beside ``init_templates``
screened template poses; without one it screens a library of template poses turned to
several headings and optimises the best few
(:func:`netepu.geometry.inverse.invert_silhouettes`). With
``warm_steps`` > 0 subjects are followed over the selected frames: a subject's first frame
starts cold, each later one warm from the subject's previous fit (``warm_steps`` Adam steps
of one start, checked against a cold start when its loss is much worse). ``smooth_frames`` > 0 then
smooths each subject's keypoints over time with a Gaussian of that standard
deviation (frames of the footage), weighing each fit by :math:`1/\text{loss}^2` so that a
failed frame pulls its neighbours little (:func:`smooth_tracks`).

A fit that faces more than a quarter turn away from its subject's fits at the neighbouring
selected frames (at most half a second away) is refitted once from its own pose turned to
their heading, and kept turned
when its loss is at most ``heading_tolerance`` times the first's
(:mod:`netepu.pipeline.heading`); then bipeds' fits are relabelled to face their travel
(:mod:`netepu.pipeline.travel`).

"A subject over time" in all of these (warm starts, smoothing, neighbouring headings, travel)
is a tracklet of the export (``tracklet_id``): its track since the tracker last forced a link
on it (:mod:`nsd.inference.tracking`), where it may have passed to another individual; an
export without tracklets: its tracks.

Templates (the inversion's starting poses) are poses of the geometry model's own
synthetic individual (:func:`template_poses`), so no training data is needed at run time.

Subject-frames are independent (a subject's chain of frames is, with warm starts), so
``workers`` processes invert them side by side, the torch threads shared among them: on
two cores two processes of one thread took 5.0 s per subject-frame of the default scene,
one process of two threads 5.9 s (docs/netepu.md).
"""

from __future__ import annotations

import logging
import os
import time
from collections import defaultdict
from collections.abc import Collection
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pycocotools import mask as mask_utils

from netepu.geometry.data import DataConfig
from netepu.geometry.initialiser import PoseInitialiser, load_initialiser
from netepu.geometry.inverse import InverseSettings, invert_silhouettes
from netepu.geometry.maps import MapSettings
from netepu.geometry.model import load_geometry_model
from netepu.pipeline.heading import NEIGHBOUR_SECONDS, heading, turned_pose, turns
from netepu.pipeline.travel import TRAVEL_SECONDS, face_travel, travel_velocity
from nsd.cameras.calibration_io import read_calibration
from nsd.core.errors import ConfigError
from nsd.core.processes import BatchPool
from nsd.export.positions import triangulate_positions
from nsd.io.embeddings import read_tracklets
from nsd.io.footage import footage_frame_rate
from nsd.io.keypoints import SubjectKeypoints, subject_groups
from nsd.ops.vectors import unit_vectors
from nsd.synth import make_individual
from nsd.synth.motion import sample_pose
from nsd.synth.skeleton import get_species

__all__ = ["invert_export", "load_initialiser_checked", "smooth_tracks", "template_poses"]

log = logging.getLogger(__name__)


def template_poses(data_cfg: dict[str, Any], n: int = 2, seed: int = 0) -> torch.Tensor:
    """``n`` random poses (n, K, 3) of the synthetic individual a geometry model was trained on."""

    cfg = DataConfig.from_mapping(data_cfg)
    ind = make_individual(
        cfg.species,
        identity=cfg.identity,
        seed=cfg.seed,
        proportion_variation=cfg.proportion_variation,
    )
    rng = np.random.default_rng(seed)
    return torch.stack(
        [ind.keypoints3d(sample_pose(ind, rng, cfg.pose_variation)).float() for _ in range(n)]
    )


# netepu.keypoints.<key>: auto, per species of the geometry model, as measured
# (docs/netepu.md "Front and back", docs/benchmarks/keypoints_travel.md): bipeds keep two
# coarsely screened templates beside the learned start and take front and back from their
# travel; a quadruped's templates brought back its tail of wrong fits (mean 275 mm against 206
# for the learned start alone) and the travel made it worse (214 against 206). A quadruped
# turned half round is refitted to its track's heading (149.8 -> 104.0 mm on three of one
# texture); bipeds, whose travel already tells front from back, gained nothing from it
# (docs/netepu.md "Front and back from the track", benchmarks/keypoints_heading_*.md)
AUTO: dict[str, dict[str, Any]] = {
    "biped": {"init_templates": 2, "travel_speed": 0.6, "heading_tolerance": 0.0},
    "quadruped": {"init_templates": 0, "travel_speed": 0.0, "heading_tolerance": 1.25},
}


def _number(value: Any) -> float:
    """``value`` as a float, NaN where it is none."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def _auto(key: str, value: Any, species: str) -> Any:
    """``value``, or for ``auto`` the species' :data:`AUTO` entry."""
    return AUTO[species][key] if value == "auto" else value


def load_initialiser_checked(path: str | os.PathLike) -> PoseInitialiser:
    """The learned initialiser at ``path``.

    Raises:
        ConfigError: a missing file or not an initialiser, naming the key.
    """
    try:
        return load_initialiser(path)
    except ValueError as e:
        raise ConfigError(f"netepu.keypoints.initialiser: {e}") from None


def _initialiser(path: str | os.PathLike, model, config: dict[str, Any]) -> PoseInitialiser:
    """The learned initialiser at ``path``, checked against the geometry model it starts.

    Raises:
        ConfigError: not an initialiser, or one made for another body (keypoints, radius).
    """
    net = load_initialiser_checked(path)
    radius = float(config["netepu"]["data"]["radius"])
    if net.cfg.n_keypoints != model.n_keypoints or abs(net.cfg.radius - radius) > 1e-6:
        raise ConfigError(
            f"netepu.keypoints.initialiser: {path} was made for {net.cfg.n_keypoints} keypoints "
            f"and a body radius of {net.cfg.radius}, the geometry model has "
            f"{model.n_keypoints} and {radius}; give the initialiser of that model's species "
            "or netepu.keypoints.initialiser=null")
    return net


def invert_export(
    export: str | os.PathLike,
    scene: str | os.PathLike,
    checkpoint: str | os.PathLike,
    out: str | os.PathLike,
    frame_step: int = 10,
    min_views: int = 2,
    min_area: int = 16,
    steps: int = 120,
    templates: int = 16,
    max_subject_frames: int = 0,
    occlusion: bool = True,
    warm_steps: int = 0,
    smooth_frames: float = 0.0,
    point_budget: int = InverseSettings.point_budget,
    init_steps: int = InverseSettings.init_steps,
    init_templates: int | str = "auto",
    init_poses: int = InverseSettings.init_poses,
    init_points_per_view: int = InverseSettings.init_points_per_view,
    inverse: dict[str, Any] | None = None,
    workers: int = 1,
    initialiser: str | os.PathLike | None = None,
    travel_speed: float | str = "auto",
    fps: float | None = None,
    only: Collection[tuple[int, int]] | None = None,
    heading_tolerance: float | str = "auto",
) -> dict[str, Any]:
    """Invert every subject of every ``frame_step``-th exported frame; writes ``keypoints3d.npz``.

    Args:
        export: an ``nsd-export`` folder.
        scene: its scene folder (for the calibration).
        checkpoint: a ``netepu-train`` geometry checkpoint.
        out: folder for ``keypoints3d.npz``.
        frame_step: invert every this many exported frames.
        min_views: subjects seen (visible area >= ``min_area`` pixels) in fewer cameras
            are skipped.
        steps: Adam steps per inversion.
        templates: candidate starting poses, each at ``inverse.headings`` headings
            (8), screened to ``inverse.screen_keep`` starts (8).
        max_subject_frames: stop after this many inversions (0: no limit).
        occlusion: other subjects' masks are occluders (module docstring).
        warm_steps: Adam steps of a warm start from the subject's previous fit (0: every
            frame starts cold).
        smooth_frames: standard deviation of the temporal smoothing, frames of the
            footage (0: none).
        point_budget: loss points per view shared by the starts alive
            (:attr:`netepu.geometry.inverse.InverseSettings.point_budget`; 0: every start
            at full points).
        init_steps: Adam steps refining the learned initialiser's start (with
            ``initialiser``).
        init_templates: screened template starts refined beside the initialiser's (``auto``:
            the species' :data:`AUTO`).
        init_poses, init_points_per_view: the templates screened beside the initialiser's
            start are the first ``init_poses`` (0: all), and a start beside it takes at most
            ``init_points_per_view`` loss points per view (the
            :class:`netepu.geometry.inverse.InverseSettings` fields).
        inverse: more :class:`netepu.geometry.inverse.InverseSettings` fields (e.g.
            ``points_per_view``; benchmarks vary them).
        initialiser: a learned initialiser's checkpoint (:mod:`netepu.geometry.initialiser`):
            cold starts refine its prediction instead of screening the templates (None: the
            templates).
        workers: processes that invert subject-frames side by side (forked, the torch
            threads shared among them: :class:`nsd.core.processes.BatchPool`); with warm
            starts each subject's frames stay in one process. The result does not depend
            on it, but on the threads each process has: sums split over more threads round
            otherwise, which a refit's 40 steps can carry to a different fit.
        only: the ``(frame, subject_id)`` subject-frames to invert (None: all); each one's
            first fit is the one it gets among all (its loss points are seeded by its frame),
            without warm starts from frames left out, and its track's neighbours for the
            heading check are the subject-frames selected.
        heading_tolerance: a fit facing more than 90 degrees away from the heading of its
            subject's neighbouring fits (at most :data:`.heading.NEIGHBOUR_SECONDS` away, at
            ``fps`` or the footage's rate) is refitted from its pose turned to it, and the refit
            replaces it when its loss is at most this many times the first's
            (:mod:`netepu.pipeline.heading`; 0: no check; ``auto``: the species'
            :data:`AUTO`).

    Returns:
        counts, the mean final silhouette loss, seconds per subject-frame (wall time over
        all workers, refits included), the share of subject-frames fitted from a warm start,
        the number relabelled front to back by their travel, the number refitted turned to
        their track's heading and how many of those refits were kept.
    """

    if frame_step < 1 or min_views < 1:
        raise ConfigError(f"frame_step and min_views must be >= 1, got {frame_step}, {min_views}")
    if workers < 1:
        raise ConfigError(f"keypoints: workers must be >= 1, got {workers}")
    if warm_steps < 0 or smooth_frames < 0:
        raise ConfigError(f"warm_steps and smooth_frames must be >= 0, got {warm_steps}, "
                          f"{smooth_frames}")
    if point_budget < 0:
        raise ConfigError(f"keypoints: point_budget must be >= 0, got {point_budget}")
    if heading_tolerance != "auto" and not _number(heading_tolerance) >= 0:  # NaN fails too
        raise ConfigError(f"keypoints: heading_tolerance must be auto or a number >= 0, got "
                          f"{heading_tolerance!r}")
    if (travel_speed != "auto" and float(travel_speed) < 0) or (fps is not None and fps <= 0):
        raise ConfigError(f"keypoints: travel_speed must be auto or >= 0 and fps > 0, got "
                          f"{travel_speed}, {fps}")
    if init_steps < 1 or (init_templates != "auto" and int(init_templates) < 0):
        raise ConfigError(f"keypoints: init_steps must be >= 1 and init_templates auto or >= 0, "
                          f"got {init_steps}, {init_templates}")
    model, config = load_geometry_model(checkpoint)
    learned = None if initialiser is None else _initialiser(initialiser, model, config)
    net = config["netepu"]
    species = DataConfig.from_mapping(net["data"]).species
    init_templates = _auto("init_templates", init_templates, species)
    travel_speed = _auto("travel_speed", travel_speed, species)
    heading_tolerance = float(_auto("heading_tolerance", heading_tolerance, species))
    starts = template_poses(net["data"], templates)
    render = net.get("render") or MapSettings.default_mapping()  # checkpoints before it: defaults
    settings = InverseSettings(steps=steps, margin=float(render["margin"]), warm_steps=warm_steps,
                               **{"point_budget": point_budget, "init_steps": init_steps,
                                  "init_templates": init_templates, "init_poses": init_poses,
                                  "init_points_per_view": init_points_per_view,
                                  **(inverse or {})})
    rig = read_calibration(scene)
    cams = rig.stacked(torch.float32)
    images, groups, n_frames = subject_groups(
        export, frame_step, lambda a, im: a["area"] >= min_area
    )
    in_image: dict[int, list[dict]] = defaultdict(list)  # every kept row, by camera-frame
    for _, anns in groups:
        for a in anns:
            in_image[int(a["image_id"])].append(a)
    tasks: list[tuple[int, int, list[dict]]] = []  # (frame, subject, its views), in order
    for (t, sid), anns in groups:
        anns = _views_of_one_size(anns, images)
        if len(anns) < min_views or (only is not None and (int(t), int(sid)) not in only):
            continue
        if max_subject_frames and len(tasks) >= max_subject_frames:
            break
        tasks.append((t, sid, anns))

    refit_settings = replace(settings, init_templates=0)  # the turned pose alone

    def fit(job: tuple[list[int], np.ndarray | None]) -> list[tuple[np.ndarray, float, bool]]:
        """``job`` ``(chain, pose)``: invert the subject-frames ``chain`` (indices into
        ``tasks``) in order, each later one warm from the one before when ``warm_steps`` (then
        a chain is one subject's); with a ``pose`` (K, 3), the chain's one subject-frame
        refitted from it alone (:mod:`.heading`)."""
        chain, pose = job
        out, previous = [], None
        for i in chain:
            t, _sid, anns = tasks[i]
            cam_idx = [rig.index(images[a["image_id"]]["camera"]) for a in anns]
            masks = torch.from_numpy(np.stack([_decode(a) for a in anns]))
            occluders = torch.from_numpy(np.stack([_others(a, in_image) for a in anns])) if (
                occlusion) else None
            previous = invert_silhouettes(
                model, masks, cams[cam_idx], starts,
                settings if pose is None else refit_settings, np.random.default_rng(t),
                occluders, previous if warm_steps and pose is None else None, learned,
                None if pose is None else torch.from_numpy(pose))
            out.append((previous.keypoints.float().numpy(), previous.loss, previous.warm))
        return out

    chains: dict[int, list[int]] = defaultdict(list)  # warm starts: one chain per tracklet
    for i, (_, sid, anns) in enumerate(tasks):
        chains[_tracklet(sid, anns) if warm_steps else i].append(i)
    results: dict[int, tuple[np.ndarray, float, bool]] = {}
    start = time.perf_counter()
    with BatchPool(fit, max(1, min(workers, len(chains))), torch.get_num_threads(),
                   "keypoints", "netepu.keypoints.workers=") as pool:
        for (chain, _), chain_fits in pool.map([(c, None) for c in chains.values()]):
            for i, (kp, loss, was_warm) in zip(chain, chain_fits, strict=True):
                results[i] = (kp, loss, was_warm)
                t, sid, anns = tasks[i]
                log.info("keypoints: frame %d subject %d from %d views, loss %.3f (%s)",
                         t, sid, len(anns), loss, "warm" if was_warm else "cold")
        refits = _turn_refits(tasks, results, species, settings.up,
                              NEIGHBOUR_SECONDS * _frame_rate(scene, rig, fps, "heading")
                              ) if heading_tolerance and tasks else {}
        turned = 0
        for ([i], _), [(kp, loss, _)] in pool.map([([i], p) for i, p in refits.items()]):
            t, sid, _ = tasks[i]
            kept = loss <= heading_tolerance * results[i][1]
            log.info("keypoints: frame %d subject %d faced away from its track: refitted turned, "
                     "loss %.3f against %.3f (%s)", t, sid, loss, results[i][1],
                     "kept" if kept else "dropped")
            if kept:
                results[i] = (kp, loss, False)
                turned += 1
    fits = [(t, sid, anns, *results[i][:2]) for i, (t, sid, anns) in enumerate(tasks)]
    warm_fits = sum(r[2] for r in results.values())
    fits, relabelled = _face_travel(fits, export, scene, rig, model.radius * travel_speed, fps,
                                    species, np.asarray(settings.up, np.float64))
    seconds = time.perf_counter() - start
    smoothed = smooth_tracks([(t, _tracklet(sid, anns), kp, loss)
                              for t, sid, anns, kp, loss in fits], smooth_frames)
    fitted = SubjectKeypoints()
    for (t, sid, anns, _, loss), kp, flip in zip(fits, smoothed, relabelled, strict=True):
        fitted.add(t, sid, anns, kp, loss, flip)
    fitted.save(Path(out) / "keypoints3d.npz", starts.shape[1])
    return fitted.summary(n_frames, "mean_loss") | {
        "seconds_per_subject_frame": seconds / len(fits) if fits else None,
        "warm_share": warm_fits / len(fits) if fits else None,
        "travel_relabelled": int(sum(relabelled)),
        "heading_refits": len(refits),
        "heading_turned": turned,
    }


def _tracklet(sid: int, anns: list[dict]) -> int:
    """The tracklet of a subject-frame (its rows' ``tracklet_id``; an export without them:
    its track ``sid``): the fits that warm-start, smooth and judge each other over time
    are a tracklet's, which the tracker vouches is one individual
    (:mod:`nsd.inference.tracking`)."""
    return int(anns[0].get("tracklet_id", sid)) if anns else int(sid)


def _turn_refits(tasks: list[tuple[int, int, list[dict]]],
                 results: dict[int, tuple[np.ndarray, float, bool]], species: str,
                 up: tuple[float, float, float], max_gap: float) -> dict[int, np.ndarray]:
    """Task index -> the fit's pose turned to the heading its track's neighbours (within
    ``max_gap`` frames) expect, for the fits that face more than :data:`.heading.MAX_TURN`
    away from it (:mod:`.heading`)."""
    rest = get_species(species).rest
    frames = [t for t, _, _ in tasks]
    subjects = [_tracklet(sid, anns) for _, sid, anns in tasks]
    headings = [heading(results[i][0], rest, up) for i in range(len(tasks))]
    return {i: turned_pose(results[i][0], angle, up).astype(np.float32)
            for i, angle in turns(frames, subjects, headings, max_gap).items()}


def _frame_rate(scene, rig, fps: float | None, what: str) -> float:
    """Frames per second: ``fps``, the footage's, or 30 with a warning saying ``what`` uses it
    (image folders have none)."""
    rate = fps or footage_frame_rate(scene, rig.names)
    if rate is None:
        log.warning("keypoints: %s has no frame rate (image folders): the %s assumes 30 "
                    "frames/s; give formats.fps", scene, what)
        rate = 30.0
    return float(rate)


def _face_travel(fits: list[tuple], export, scene, rig, min_speed: float, fps: float | None,
                 species: str, up: np.ndarray) -> tuple[list[tuple], list[bool]]:
    """``fits`` ``(frame, subject, rows, keypoints, loss)`` with each pose that faces against
    its subject's travel at ``min_speed`` (scene units per second) or more relabelled
    (:mod:`netepu.pipeline.travel`), and which were."""
    if min_speed <= 0 or not fits:
        return fits, [False] * len(fits)
    rate = _frame_rate(scene, rig, fps, "travel that tells front from back")
    d = max(1, round(TRAVEL_SECONDS * rate))
    positions = triangulate_positions(
        export, rig, frames={t + s for t, *_ in fits for s in (-d, d)})
    pieces = read_tracklets(export) or {}
    body = get_species(species)
    left, mirror = body.left_index(), body.mirror_index()
    up = unit_vectors(up)
    out, flips = [], []
    for t, sid, anns, kp, loss in fits:
        velocity = travel_velocity(positions, t, sid, d, rate, up)
        if len({pieces.get((t + s, sid)) for s in (-d, 0, d)}) > 1:
            velocity = None  # the track was forced on between: maybe another individual
        kp, flip = face_travel(np.asarray(kp), velocity, left, mirror, up, min_speed)
        if flip:
            log.info("keypoints: frame %d subject %d faced against its travel: left and right "
                     "swapped", t, sid)
        out.append((t, sid, anns, kp, loss))
        flips.append(flip)
    return out, flips


def smooth_tracks(fits: list[tuple[int, int, np.ndarray, float]], sigma: float) -> list[np.ndarray]:
    r"""Each subject's keypoints smoothed over its frames (module docstring).

    Args:
        fits: ``(frame, subject, keypoints (K, 3), loss)`` per subject-frame.
        sigma: the Gaussian's standard deviation in frames (0: the keypoints unchanged).

    Returns:
        the smoothed keypoints, in the order of ``fits``: the mean of the subject's fits
        within 3 sigma, weighted by :math:`e^{-\Delta t^2 / 2\sigma^2} / \text{loss}^2`.
    """
    if sigma <= 0:
        return [np.asarray(kp) for _, _, kp, _ in fits]
    tracks: dict[int, list[int]] = defaultdict(list)
    for i, (_, sid, _, _) in enumerate(fits):
        tracks[sid].append(i)
    out: list[np.ndarray] = [np.empty(0)] * len(fits)
    for rows in tracks.values():
        t = np.array([fits[i][0] for i in rows], np.float64)
        kp = np.stack([np.asarray(fits[i][2], np.float64) for i in rows])
        quality = 1.0 / np.maximum([fits[i][3] for i in rows], 1e-6) ** 2
        for j, i in enumerate(rows):
            d = t - t[j]
            w = np.exp(-0.5 * (d / sigma) ** 2) * quality * (np.abs(d) <= 3 * sigma)
            out[i] = np.tensordot(w / w.sum(), kp, 1)
    return out


def _decode(a: dict) -> np.ndarray:
    """A row's mask, (H, W) bool."""
    return mask_utils.decode(a["segmentation"]).astype(bool)


def _others(a: dict, in_image: dict[int, list[dict]]) -> np.ndarray:
    """The union of the other subjects' masks in row ``a``'s camera-frame, (H, W) bool
    (merged as run-length encodings, decoded once)."""
    others = [b["segmentation"] for b in in_image[int(a["image_id"])]
              if b["subject_id"] != a["subject_id"]]
    if not others:
        return np.zeros(tuple(a["segmentation"]["size"]), bool)
    return mask_utils.decode(mask_utils.merge(others)).astype(bool)


def _views_of_one_size(anns: list[dict], images: dict[int, dict]) -> list[dict]:
    """The subject's views whose images share the most common size: the inversion takes
    one (V, H, W) stack of masks."""

    def size(a: dict) -> tuple[int, int]:
        im = images[a["image_id"]]
        return int(im["height"]), int(im["width"])

    sizes = [size(a) for a in anns]
    if len(set(sizes)) == 1:
        return anns
    common = max(set(sizes), key=sizes.count)
    return [a for a, s in zip(anns, sizes, strict=True) if s == common]
