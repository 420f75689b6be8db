"""Where the hull cannot settle: who owns the pixels near two individuals, hull or learned.

    .venv/bin/python tools/bench_contested.py RUN [RUN ...] --label NAME ...   # nsd-run folders

The exported masks give each foreground pixel to a window: by the learned ownership (the
composited weights and the decoded colours), plus a bonus for the window of the pixel's
visual-hull individual (``inference.hull_ownership``), which is ``inference.hull_contested``
instead where voxels of two or more individuals project within ``--band`` voxel sides
(:func:`nsd.cues.occupancy.contested_pixels`): there the hull's owner is a guess (touching
bodies, one in front of another). This script measures that guess against ground truth.

For each run (an ``nsd-run`` folder with ``train/checkpoint.pt`` and the scene of its
``scene/stage.json``), on the first ``--frames`` held-out frames, every visible foreground
pixel of every view (ground truth visible and foreground evidence above 0.5) is marked
contested or not, for each band, and each way of owning pixels is scored by the share of
those pixels it gives to the window matched (Hungarian on mask IoU, as ``nsd-eval``) to the
pixel's individual:

* ``hull``: the hull's owners alone (:mod:`nsd.evaluation.hull_baseline`);
* ``hull + colour models``: no learning either: the hull's owner where it can settle it, and
  on contested pixels the individual near the pixel whose colour model (counted on the
  pixels the hull settles, pooled over the views; :mod:`nsd.inference.colour_models` with the
  shipped weight and bins) likes the pixel's colour best;
* ``learned``: the learned ownership alone (both bonuses 0; with the colour models where the
  shipped defaults have them, as in the next two);
* ``hull bonus``: the bonus of ``hull_ownership`` on every pixel (``hull_contested`` equal);
* ``shipped, no colour models``: this commit's inference defaults with
  ``inference.colour_model=0``;
* ``shipped``: this commit's inference defaults (on contested pixels, only the windows of
  the individuals near them may own them; the individuals' colour models).

``ideal_mask_miou``: the mask mIoU (``nsd-eval``'s) if every foreground pixel went to its
true individual, the most any ownership can score with this foreground cut; ``<way>: mask
mIoU``: each way's own (``nsd-eval``'s mask mIoU on the same frames).

Writes ``docs/benchmarks/<--report>.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nsd.cues.evidence import foreground_evidence
from nsd.cues.occupancy import CONTEST_BAND, multiview_proposals
from nsd.evaluation.contact import touches
from nsd.evaluation.decomposition import Tally, instant_truth, score_views
from nsd.evaluation.hull_baseline import HullDecomposition
from nsd.inference.multiview import InferenceSettings, decompose_views
from nsd.io.ground_truth import GroundTruth
from nsd.io.scene_data import SceneData
from nsd.model.checkpoint import load_decomposition
from nsd.ops.boxes import mask_iou, match
from tools.benchlib import write_report

METHODS = ("hull", "hull + colour models", "learned", "hull bonus",
           "shipped, no colour models", "shipped")


def _owner_of_truth(masks: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(H, W) the window each pixel's individual is matched to (-2: unmatched, -1: none),
    for masks (N, H, W) and ground-truth visible masks (G, H, W)."""
    g2w = {g: w for w, g in match(mask_iou(masks, visible))}
    truth = np.where(visible.any(0), visible.argmax(0), -1)
    return np.vectorize(lambda g: g2w.get(g, -2) if g >= 0 else -1, otypes=[np.int64])(truth)


def _owners(masks: np.ndarray) -> np.ndarray:
    """(H, W) the window owning each pixel of masks (N, H, W), -1 where none."""
    return np.where(masks.any(0), masks.argmax(0), -1)


def _windows(masks: torch.Tensor, depths: torch.Tensor) -> HullDecomposition:
    """Masks (V, k, H, W) and depths (V, k) as a decomposition (scored by nsd-eval's code);
    a window is active where its mask is not empty."""
    active = masks.flatten(2).sum(-1) > 0
    return HullDecomposition(masks, masks, depths, active.float(), active)


def _ideal(truths, fg: torch.Tensor, k: int) -> HullDecomposition:
    """Every foreground pixel (fg (V, H, W)) given to its true individual, as windows."""
    V, (H, W) = len(truths), fg.shape[-2:]
    masks = torch.zeros(V, k, H, W)
    for v, truth in enumerate(truths):
        n = min(k, len(truth.visible))
        masks[v, :n] = torch.as_tensor(truth.visible[:n]) & fg[v]
    return _windows(masks, torch.zeros(V, k))


def _as_windows(owners: torch.Tensor, depths: torch.Tensor, k: int) -> HullDecomposition:
    """(V, H, W) owners in [-1, k) as a decomposition of k windows."""
    return _windows((owners[:, None] == torch.arange(k)[None, :, None, None]).float(), depths)


def _hull_colour_owners(hull, views: torch.Tensor, fg: torch.Tensor, models) -> torch.Tensor:
    """The hull's owners, with each contested pixel given to the individual near it whose
    colour model likes its colour best (the models counted on the uncontested pixels the
    hull owns, one per individual over all views)."""
    V, k = hull.candidates.shape[:2]
    slots = torch.arange(k)[None, :, None, None]
    owned = hull.owners[:, None] == slots  # (V, k, H, W)
    settled = (hull.owners >= 0) & ~hull.contested
    allowed = torch.where(hull.contested[:, None], hull.candidates, owned)
    score = torch.where(allowed, 0.0, -1e4)  # ties among the candidates of a contested pixel
    score = models.rescore(score, views, fg & (settled | hull.contested),
                           torch.arange(k).expand(V, k))
    best = score.argmax(1)
    return torch.where(hull.contested & fg & allowed.any(1), best, hull.owners)


def score_run(run: Path, frames: int, bands: list[float]) -> tuple[dict, float, dict]:
    """Per band and method: [right, pixels] on contested and on other pixels; the ideal
    ownership's mask mIoU; and each method's."""
    scene = json.loads((run / "scene" / "stage.json").read_text())["summary"]["path"]
    trained = load_decomposition(run / "train" / "checkpoint.pt", torch.device("cpu"))
    cfg = trained.config
    H, W = trained.frame_hw
    data = SceneData(scene, (W, H), cfg.data.cameras, cfg.data.val_fraction,
                     cfg.data.max_frames, cfg.data.get("units", "auto"),
                     cfg.data.get("frame_stride", 1), cfg.data.get("background", "median"))
    gt = GroundTruth.load(scene)
    shipped = InferenceSettings.defaults()
    settings = {
        "learned": dataclasses.replace(shipped, hull_ownership=0.0, hull_contested=0.0),
        "hull bonus": dataclasses.replace(shipped, hull_contested=shipped.hull_ownership),
        "shipped, no colour models": dataclasses.replace(shipped, colour_model=0.0),
        "shipped": shipped,
    }
    grid = shipped.grid(data.rig, data.frame_hw)
    k, split = trained.model.cfg.num_windows, not trained.model.detector.use_presence
    idx = np.asarray(data.heldout_frames)
    idx = idx[np.linspace(0, len(idx) - 1, min(frames, len(idx))).round().astype(int)]
    tally = {b: {m: np.zeros((2, 2)) for m in METHODS} for b in bands}
    ideal = Tally()
    tallies = {m: Tally() for m in METHODS}
    for t in idx:
        views, bgs = data.views(int(t))
        V = views.shape[0]
        ev = foreground_evidence(views, bgs)
        hulls = {b: multiview_proposals(ev, grid, k, split=split, contest=b) for b in bands}
        decs = {m: decompose_views(trained.model, views, bgs, V, s, grid)
                for m, s in settings.items()}
        truths = instant_truth(gt, data, int(t))
        touching = touches(truths)
        score_views(_ideal(truths, ev > 0.5, k), truths, 0.5, ideal.counts(touching))
        shipped_hull = multiview_proposals(ev, grid, k, split=split, contest=CONTEST_BAND)
        decs["hull"] = _as_windows(shipped_hull.owners, shipped_hull.depths, k)
        decs["hull + colour models"] = _as_windows(
            _hull_colour_owners(shipped_hull, views, ev > 0.5, shipped.colour_models),
            shipped_hull.depths, k)
        for m, dec in decs.items():
            score_views(dec, truths, 0.5, tallies[m].counts(touching))
        for v, truth in enumerate(truths):
            owners = {}
            for m, dec in decs.items():
                owners[m] = (dec.masks[v] > 0.5).numpy() & dec.active[v].numpy()[:, None, None]
            pixels = truth.visible.any(0) & (ev[v] > 0.5).numpy()
            for m, masks in owners.items():
                right = _owners(masks) == _owner_of_truth(masks, truth.visible)
                for b in bands:
                    hard = hulls[b].contested[v].numpy()
                    for c, where in enumerate((pixels & hard, pixels & ~hard)):
                        tally[b][m][c] += (right[where].sum(), where.sum())
    return tally, float(ideal.metrics()["mask_miou"]), {
        m: float(t.metrics()["mask_miou"]) for m, t in tallies.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+", help="nsd-run output folders")
    ap.add_argument("--label", nargs="*", default=[], help="a name per run")
    ap.add_argument("--frames", type=int, default=30, help="held-out frames per run")
    ap.add_argument("--band", type=float, nargs="+", default=[0.6, CONTEST_BAND, 3.0],
                    help="contested_pixels' bands, in voxel sides")
    ap.add_argument("--report", default="contested", help="docs/benchmarks/<report>.{md,json}")
    args = ap.parse_args()
    if args.label and len(args.label) != len(args.runs):
        raise SystemExit(f"--label: {len(args.label)} names for {len(args.runs)} runs")
    torch.set_num_threads(1)
    rows = []
    for name, run in zip(args.label or [r.name for r in args.runs], args.runs, strict=True):
        tally, ideal, miou = score_run(run, args.frames, args.band)
        for b in args.band:
            t = tally[b]
            n_hard, n_easy = t["hull"][0][1], t["hull"][1][1]
            row = {"run": name, "band": b, "contested_share": n_hard / max(n_hard + n_easy, 1),
                   "ideal_mask_miou": ideal}
            for m in METHODS:
                row[f"{m}: contested"] = t[m][0][0] / max(t[m][0][1], 1)
                row[f"{m}: other"] = t[m][1][0] / max(t[m][1][1], 1)
                row[f"{m}: mask mIoU"] = miou[m]
            rows.append(row)
            print(row, flush=True)
    shipped = InferenceSettings.defaults()
    notes = (f"Share of the visible foreground pixels (ground truth visible, evidence > 0.5) "
             f"that each way of owning pixels gives to the window matched to their individual, "
             f"on contested pixels (voxels of two or more hull individuals within `band` voxel "
             f"sides) and on the others; first {args.frames} held-out frames per run. "
             f"`hull bonus`: `hull_ownership` = `hull_contested` = "
             f"{shipped.hull_ownership:g}; `shipped`: `hull_ownership` "
             f"{shipped.hull_ownership:g}, `hull_contested` {shipped.hull_contested:g} "
             f"(band {CONTEST_BAND:g}); colour agreement {shipped.colour_sigma:g} throughout; "
             f"colour models: weight {shipped.colour_model:g}, {shipped.colour_model_bins} "
             f"levels per channel, margin {shipped.colour_model_margin:g}.")
    write_report(args.report, "Where the hull cannot settle: contested pixels, hull or learned",
                 rows, notes)


if __name__ == "__main__":
    main()
