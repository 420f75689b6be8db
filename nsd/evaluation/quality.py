"""A label-free quality report of an export: whether to trust a run on footage without
ground truth.

Every figure is computed from the footage, the calibration and the export alone, at the
training size, over up to ``max_frames`` frames spread evenly over the export:

* **explained**: share of the background-residual foreground (foreground evidence > 0.5,
  :func:`nsd.cues.evidence.foreground_evidence` against the run's background) that some
  exported visible mask covers. Low: subjects were missed (or the background is wrong).
* **spill**: share of the masks' pixels where the residual sees only background. High:
  masks on empty floor.
* **consistency**: per camera-frame, the share of its exported masks' pixels (their union)
  inside the visual hull of the *other* cameras' masks (voxels that every other camera
  seeing them puts inside a mask, at least two of them), projected into it: a mask, or a
  part of one, that the other cameras do not confirm lowers it (the hull of a few views is
  fatter than the body, so the other direction says little). Needs three or more cameras.
* **identity switches**: share of consecutive rows of a per-camera track (``subject_id``)
  whose identity changes; **view agreement**: share of the subjects of a frame seen by
  several cameras to which every camera gives the same identity (a subject is one
  cross-view association, so disagreement is an association or identity error).
* **count changes**: share of frames whose number of subjects (distinct identities, or
  subject ids without identities) differs from the previous analysed frame's.
* **individuals**: the distinct identities over the analysed frames (with identities). Fewer
  than the run was told there are (``model.num_windows`` with a fixed count) warns: a window
  then holds two bodies that touch, or two windows share one body, on every camera alike,
  which none of the figures above can see (2 bipeds beside 2 cows on 5 cameras: 3
  individuals named, every other figure within its limit; docs/nsd.md, "Found, not mended").
* **hull_bodies**: the separate bodies the visual hull shows in frames spread over the
  footage (:func:`nsd.cues.count.scene_bodies`, a lower bound on the individuals; NaN for
  footage too short or with too few cameras, :func:`nsd.cues.count.countable`). Fewer identities
  than that warns too, whatever the run was told: five individuals run with two windows
  named 2, every figure above within its limit (docs/nsd.md, "How many individuals the hull
  shows").

Frames are ranked by ``badness`` = (1 - explained) + spill + (1 - consistency), each the
mean over the frame's cameras; the worst ones are worth a look (``worst``).
"""

from __future__ import annotations

import itertools
import json
import os
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from pycocotools import mask as mask_utils

from nsd.cues.count import countable, footage_bodies
from nsd.cues.evidence import foreground_evidence
from nsd.cues.occupancy import voxel_grid
from nsd.io.footage import MultiViewFootage

__all__ = ["TRUST_LIMITS", "FrameQuality", "QualityReport", "quality_markdown", "quality_report",
           "reprojected_hulls"]

HULL_RESOLUTION = 96  # voxels per side of the working volume (48: limbs fall between voxels)
MIN_OTHER_VIEWS = 2  # the hull of the other cameras needs this many of them to see a voxel
# limits past which the report warns (each a share): the run is then not to be trusted blind.
# Set between the good and the bad runs of docs/benchmarks/quality.md (a run with identity
# accuracy 0.98 has 6 % switches and 79 % view agreement; runs at 0.47-0.66 have 20-38 % and
# 5-20 %); held-out footage may need others.
TRUST_LIMITS = {"explained": 0.8, "spill": 0.2, "consistency": 0.8, "identity_switches": 0.1,
                "view_agreement": 0.6, "count_changes": 0.1}


@dataclass
class FrameQuality:
    """The label-free figures of one frame; per camera lists follow ``cameras``."""

    frame: int
    explained: list[float]
    spill: list[float]
    consistency: list[float]
    subjects: int

    @property
    def badness(self) -> float:
        """(1 - explained) + spill + (1 - consistency), means over cameras (NaN ignored)."""
        parts = [1 - _mean(self.explained), _mean(self.spill), 1 - _mean(self.consistency)]
        return float(sum(p for p in parts if np.isfinite(p)))


@dataclass
class QualityReport:
    """Summary figures (means over the analysed frames), per-frame figures, the worst frames
    and the warnings of the figures past :data:`TRUST_LIMITS`."""

    cameras: list[str]
    frames: list[FrameQuality]
    summary: dict[str, float]
    warnings: list[str] = field(default_factory=list)

    def worst(self, n: int) -> list[int]:
        """The ``n`` frames of highest badness, worst first."""
        ranked = sorted(self.frames, key=lambda f: -f.badness)
        return [f.frame for f in ranked[:n]]

    def to_json(self) -> dict[str, Any]:
        """Plain data; NaN (a figure that does not apply) becomes None."""
        return {
            "summary": {k: v if np.isfinite(v) else None for k, v in self.summary.items()},
            "warnings": self.warnings, "cameras": self.cameras,
            "frames": [{"frame": f.frame, "badness": round(f.badness, 4),
                        "subjects": f.subjects,
                        **{k: [round(x, 4) if np.isfinite(x) else None
                               for x in getattr(f, k)]
                           for k in ("explained", "spill", "consistency")}}
                       for f in self.frames],
        }  # fmt: skip


def _mean(x) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else float("nan")


def reprojected_hulls(masks: np.ndarray, grid, dilate: int) -> np.ndarray:
    """For every view, the visual hull of the other views' masks projected into it.

    Args:
        masks: (V, H, W) bool, the views' masks.
        grid: :class:`nsd.cues.occupancy.VoxelGrid` of these views and size.
        dilate: pixels by which the projected voxel centres are grown (a voxel's footprint).

    Returns:
        (V, H, W) bool.
    """
    V, H, W = masks.shape
    fg = torch.from_numpy(masks.reshape(V, -1))
    hit = torch.gather(fg, 1, grid.pixel) & grid.inside  # (V, M), one gather for all views
    near = hit.sum(0) >= MIN_OTHER_VIEWS  # only these can be in a hull of the others
    hit, inside, pixel = hit[:, near], grid.inside[:, near], grid.pixel[:, near]
    carved = ~hit & inside  # the view sees the voxel outside every mask
    out = np.zeros((V, H * W), np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1))
    for v in range(V):
        others = torch.arange(V) != v
        occupied = (~carved[others].any(0) & (inside[others].sum(0) >= MIN_OTHER_VIEWS)
                    & hit[others].any(0) & inside[v])
        out[v, pixel[v][occupied].numpy()] = 1
    out = out.reshape(V, H, W)
    if dilate > 0:
        out = np.stack([cv2.dilate(m, kernel) for m in out])
    return out.astype(bool)


def _covered(mask: np.ndarray, hull: np.ndarray) -> float:
    """Share of ``mask``'s pixels inside ``hull`` (NaN for an empty mask): a hull of a few
    views is fatter than the body, so only this direction says whether the views agree."""
    n = mask.sum()
    return float((mask & hull).sum() / n) if n else float("nan")


def _rows(coco: dict) -> tuple[dict, dict]:
    """(camera, frame) -> annotations, and the images by that key."""
    images = {im["id"]: im for im in coco["images"]}
    by_key: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        by_key[(im["camera"], int(im["frame"]))].append(a)
    return by_key, {(im["camera"], int(im["frame"])): im for im in coco["images"]}


def _identity_figures(coco: dict, identity: dict[int, int] | None,
                      frames: list[int]) -> dict[str, float]:
    """Identity switches along tracks, view agreement and count changes (rows without an
    identity, -1, are left out)."""
    tracks: dict[tuple[str, int], list[tuple[int, int]]] = defaultdict(list)
    views: dict[tuple[int, int], dict[str, int]] = defaultdict(dict)  # (frame, subject): cams
    per_frame: dict[int, set[int]] = defaultdict(set)
    for a in coco["annotations"]:
        i = int(a["subject_id"]) if identity is None else identity.get(int(a["id"]), -1)
        if i < 0:
            continue
        t, s = int(a["frame"]), int(a["subject_id"])
        tracks[(a["camera"], s)].append((t, i))
        views[(t, s)][a["camera"]] = i
        per_frame[t].add(i)
    steps = switches = 0
    for rows in tracks.values():
        seq = [i for _, i in sorted(rows)]
        steps += len(seq) - 1
        switches += sum(a != b for a, b in itertools.pairwise(seq))
    agree = [len(set(c.values())) == 1 for c in views.values() if len(c) > 1]
    counts = [len(per_frame.get(t, ())) for t in frames]
    changes = sum(a != b for a, b in itertools.pairwise(counts))
    return {
        "identity_switches": switches / steps if steps else float("nan"),
        "view_agreement": float(np.mean(agree)) if agree else float("nan"),
        "count_changes": changes / (len(counts) - 1) if len(counts) > 1 else float("nan"),
        "subjects_median": float(np.median(counts)) if counts else float("nan"),
        "individuals": (float(len(set().union(*per_frame.values()))) if identity is not None
                        else float("nan")),
    }


def quality_report(
    export: str | os.PathLike,
    scene: str | os.PathLike,
    image_size: tuple[int, int],
    identity: dict[int, int] | None = None,
    background: str = "median",
    units: str = "auto",
    max_frames: int = 100,
    individuals: int | None = None,
    resolution: int = 48,
    min_views: int | str = "auto",
) -> QualityReport:
    """The label-free quality of an ``nsd-export`` folder (module docstring).

    Args:
        export: the export folder (``subjects.coco.json``).
        scene: its scene folder.
        image_size: (W, H) at which everything is compared (the training size).
        identity: annotation id -> identity (``identities.csv``); None: the export's tracks.
        background: the run's background method (``data.background``).
        units: the calibration's length unit (``data.units``).
        max_frames: frames analysed, spread evenly over the export (0: all).
        individuals: how many individuals the run was told the scene holds (None: not
            known, e.g. ``num_windows`` an upper bound); fewer identities warn.
        resolution, min_views: the voxel grid in which the hull's bodies are counted (the
            run's ``prior_proposal.resolution`` and ``prior_proposal.min_views``).
    """
    coco = json.loads((Path(export) / "subjects.coco.json").read_text())
    by_key, images = _rows(coco)
    cams = sorted({c for c, _ in images}, key=str)
    footage = MultiViewFootage(scene, cams, tuple(image_size), units=units,
                               background=background)
    cams = footage.camera_names
    W, H = footage.rig[0].size
    all_frames = sorted({t for _, t in images})
    if max_frames and len(all_frames) > max_frames:
        pick = np.unique(np.linspace(0, len(all_frames) - 1, max_frames).round().astype(int))
        all_frames = [all_frames[i] for i in pick]
    bgs = torch.stack([torch.from_numpy(cv2.resize(footage.background_estimate(v).image,
                                                   (W, H), interpolation=cv2.INTER_AREA))
                       for v in range(len(cams))]).permute(0, 3, 1, 2).float() / 255
    # two views, as when the report's limits were set (docs/benchmarks/quality.md)
    grid = voxel_grid(footage.rig, (H, W), HULL_RESOLUTION, min_views=2)
    voxel_px = float((grid.focal.mean() * grid.size / grid.depth[grid.inside].median()).item())
    dilate = max(1, round(voxel_px))  # a voxel's footprint around its centre
    frames = []
    for t in all_frames:
        img = torch.from_numpy(footage.frame(t)).permute(0, 3, 1, 2).float() / 255
        fg = (foreground_evidence(img, bgs) > 0.5).numpy()
        union = np.zeros((len(cams), H, W), bool)
        for v, cam in enumerate(cams):
            for a in by_key.get((cam, t), []):
                m = mask_utils.decode(a["segmentation"])
                union[v] |= cv2.resize(m, (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)
        explained = [float((fg[v] & union[v]).sum() / fg[v].sum()) if fg[v].any()
                     else float("nan") for v in range(len(cams))]
        spill = [float((union[v] & ~fg[v]).sum() / union[v].sum()) if union[v].any()
                 else float("nan") for v in range(len(cams))]
        hulls = reprojected_hulls(union, grid, dilate) if len(cams) >= 3 else None
        consistency = ([_covered(union[v], hulls[v]) for v in range(len(cams))]
                       if hulls is not None else [float("nan")] * len(cams))
        subjects = len({a["subject_id"] for c in cams for a in by_key.get((c, t), [])})
        frames.append(FrameQuality(t, explained, spill, consistency, subjects))
    summary = {
        "frames": float(len(frames)),
        "hull_bodies": _hull_bodies(footage, bgs, resolution, min_views),
        "explained": _mean([_mean(f.explained) for f in frames]),
        "spill": _mean([_mean(f.spill) for f in frames]),
        "consistency": _mean([_mean(f.consistency) for f in frames]),
        **_identity_figures(coco, identity, all_frames),
    }
    for c, v in enumerate(cams):
        summary[f"explained/{v}"] = _mean([f.explained[c] for f in frames])
        summary[f"consistency/{v}"] = _mean([f.consistency[c] for f in frames])
    return QualityReport(cams, frames, summary, _warnings(summary, cams, individuals))


def _hull_bodies(footage: MultiViewFootage, backgrounds: torch.Tensor, resolution: int,
                 min_views: int | str) -> float:
    """The bodies the visual hull shows in frames spread over the footage (module
    docstring), NaN where the footage is too short or has too few cameras."""
    if not countable(footage.num_frames, footage.num_views):
        return float("nan")
    W, H = footage.rig[0].size
    return float(footage_bodies(lambda t: foreground_evidence(
        torch.from_numpy(footage.frame(int(t))).permute(0, 3, 1, 2).float() / 255,
        backgrounds), footage.num_frames, footage.rig, (H, W), resolution, min_views)[0])


def _warnings(s: dict[str, float], cams: list[str], individuals: int | None = None) -> list[str]:
    lim, out = TRUST_LIMITS, []
    if individuals is not None and s["individuals"] < individuals:  # NaN: no identities
        out.append(f"the identities name {int(s['individuals'])} individuals where the run was "
                   f"told of {individuals} (model.num_windows): a window holds two bodies that "
                   "touch, or two windows share one body, in every camera alike; look at the "
                   "worst frames and at grids/")
    elif s["individuals"] < s.get("hull_bodies", float("nan")):  # NaN either: no warning
        out.append(f"the identities name {int(s['individuals'])} individuals where the visual "
                   f"hull shows at least {int(s['hull_bodies'])} separate bodies: a window "
                   "holds several bodies, in every camera alike (too few windows: set "
                   "model.num_windows to the number of individuals); look at grids/")
    if s["explained"] < lim["explained"]:
        low = [c for c in cams if s[f"explained/{c}"] < lim["explained"]]
        out.append(f"only {s['explained']:.0%} of the moving pixels are in some subject's mask "
                   f"(cameras {', '.join(low)}): subjects are missed, or the background is "
                   "wrong (see scene/background/)")
    if s["spill"] > lim["spill"]:
        out.append(f"{s['spill']:.0%} of the masks' pixels show only background: masks spill "
                   "onto the floor")
    if s["consistency"] < lim["consistency"]:
        out.append(f"only {s['consistency']:.0%} of the masks' pixels are confirmed by the "
                   "other cameras' hull: check the calibration (nsd-calib) and the worst frames")
    if s["identity_switches"] > lim["identity_switches"]:
        out.append(f"identities change along {s['identity_switches']:.0%} of the tracks' steps")
    if s["view_agreement"] < lim["view_agreement"]:
        out.append(f"the cameras agree on the identity of only {s['view_agreement']:.0%} of the "
                   "subjects seen by several of them")
    if s["count_changes"] > lim["count_changes"]:
        out.append(f"the number of subjects changes in {s['count_changes']:.0%} of the frames")
    return out


def quality_markdown(report: QualityReport, worst: list[int]) -> str:
    """``quality.md``: the figures beside their limits, the warnings, the worst frames."""
    s = report.summary
    lines = ["# Label-free quality of this run", "",
             f"{int(s['frames'])} frames analysed; no ground truth used "
             "(nsd/evaluation/quality.py says how each figure is made).", "",
             "| figure | value | warns when |", "|---|---|---|"]
    for key, limit in TRUST_LIMITS.items():
        side = "<" if key in ("explained", "consistency", "view_agreement") else ">"
        value = s.get(key, float("nan"))
        lines.append(f"| {key} | {value:.3f} | {side} {limit} |")
    bodies, named = s.get("hull_bodies", float("nan")), s.get("individuals", float("nan"))
    lines += ["", (f"The visual hull shows at least {bodies:.0f} separate "
                   f"bod{'y' if bodies == 1 else 'ies'}"
                   if np.isfinite(bodies) else "The visual hull's bodies were not counted "
                   "(footage too short or too few cameras)")
              + (f"; the identities name {named:.0f} individual{'' if named == 1 else 's'}."
                 if np.isfinite(named) else "."),
              "", "| camera | explained | consistency |", "|---|---|---|"]
    lines += [f"| {c} | {s[f'explained/{c}']:.3f} | {s[f'consistency/{c}']:.3f} |"
              for c in report.cameras]
    lines += ["", "## Warnings", ""]
    lines += [f"- {w}" for w in report.warnings] or ["- none"]
    lines += ["", "## Worst frames (worst/frame_<t>.png)", ""]
    by_frame = {f.frame: f for f in report.frames}
    lines += [f"- frame {t}: badness {by_frame[t].badness:.3f}" for t in worst] or ["- none"]
    return "\n".join(lines) + "\n"
