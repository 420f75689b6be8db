"""Decomposition metrics against ground truth (used by ``nsd-eval`` and every later issue).

Per camera-frame, predicted subjects (active windows) are matched one-to-one to
the ground-truth individuals that are at least partly visible (Hungarian
matching on visible-mask IoU). Then:

* **detection rate**: fraction of GT individuals whose matched prediction's box
  (the tight box of its visible mask; a focal window is larger than its
  subject, so the window itself is not the detection) has IoU >= 0.5 with the
  GT visible box;
* **mask detection rate**: fraction of GT individuals whose matched prediction's
  visible mask has IoU >= 0.5 with the GT visible mask (neither count is the
  stricter: a box can reach 0.5 around a mask that lies on another body, and the
  box of a body seen in pieces can miss it while the mask holds most of it);
* **mask mIoU**: mean visible-mask IoU over GT individuals (0 when unmatched);
* **foreground ARI**: adjusted Rand index (scikit-learn) between GT and
  predicted instance labels over GT foreground pixels;
* **depth-order accuracy**: over GT pairs whose amodal masks overlap (>= 4
  pixels) and are both matched: the GT front individual is the one that owns
  most of the overlap's visible pixels; correct when its window has the smaller
  predicted depth;
* **cross-view association accuracy**: for each frame, view pair (v, w) and GT
  individual matched in both views, the hard association of its window in v
  (the model's score: appearance, plus ray distance if configured) picks its
  window in w;
* **merge rate**: over camera-frames with >= 2 visible GT individuals, the
  fraction where one window's mask covers at least half of the visible mask of
  two or more of them (the auto-encoder's failure in the NSD paper);
* **overlap ownership**: over visible pixels inside GT amodal overlaps, the
  fraction whose strongest window is the one matched to the pixel's GT owner
  (blended overlaps, NSD's failure without depth, lower it);
* **novel-view PSNR / SSIM**: Bi-NVS re-synthesis of view w from view v;
* **COCO AP** (bbox and segm, class-agnostic) through pycocotools COCOeval on
  the scene's COCO ground truth.

The metrics of :data:`SPLIT_METRICS` are also reported over the instants where the
individuals are apart and those where they touch (:mod:`nsd.evaluation.contact`).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from dataclasses import dataclass, field

import kornia
import numpy as np
import torch
from pycocotools.cocoeval import COCOeval
from sklearn.metrics import adjusted_rand_score
from torch import Tensor

from nsd.core.device import call_on_device
from nsd.cues.clustering import ClusterTrack
from nsd.evaluation.contact import MIN_OVERLAP, PARTS, touches
from nsd.inference.association_scores import association_scores
from nsd.inference.multiview import InferenceSettings, decompose_views, model_scene_track
from nsd.io.coco_results import decomposition_to_coco
from nsd.ops.boxes import box_iou_xywh, mask_boxes_xywh, mask_iou, match
from nsd.ops.ssim import ssim_map

__all__ = [
    "SPLIT_METRICS",
    "Counts",
    "FrameScore",
    "Tally",
    "coco_ap",
    "count_associations",
    "evaluate_model",
    "fg_ari",
    "instant_truth",
    "score_frame",
    "score_views",
]

def fg_ari(gt_labels: np.ndarray, pred_labels: np.ndarray) -> float:
    """Adjusted Rand index over GT foreground pixels (gt label >= 0); nan without foreground."""
    fg = gt_labels >= 0
    if fg.sum() == 0 or len(np.unique(gt_labels[fg])) < 1:
        return float("nan")
    return float(adjusted_rand_score(gt_labels[fg], pred_labels[fg]))


@dataclass
class FrameScore:
    """Counts from one camera-frame; summed over frames by :func:`evaluate_model`."""

    n_gt: int = 0
    detected: int = 0
    mask_detected: int = 0  # matched with visible-mask IoU >= 0.5
    iou_sum: float = 0.0
    order_total: int = 0
    order_correct: int = 0
    ari: list[float] = field(default_factory=list)
    multi: int = 0  # camera-frames with >= 2 visible GT individuals
    merged: int = 0  # ... of which one window covers half of two of them
    overlap_pixels: int = 0
    overlap_owned: int = 0
    matches: dict[int, int] = field(default_factory=dict)  # gt identity -> predicted window

    def add(self, other: FrameScore) -> None:
        """Add ``other``'s counts to these (``matches`` are per camera-frame, not summed)."""
        self.n_gt += other.n_gt
        self.detected += other.detected
        self.mask_detected += other.mask_detected
        self.iou_sum += other.iou_sum
        self.order_total += other.order_total
        self.order_correct += other.order_correct
        self.ari += other.ari
        self.multi += other.multi
        self.merged += other.merged
        self.overlap_pixels += other.overlap_pixels
        self.overlap_owned += other.overlap_owned


def score_frame(
    pred_masks: np.ndarray,
    pred_depths: np.ndarray,
    active: np.ndarray,
    gt_visible: np.ndarray,
    gt_amodal: np.ndarray,
    gt_boxes: np.ndarray,
    gt_ids: Sequence[int],
    threshold: float = 0.5,
) -> FrameScore:
    """Score one camera-frame.

    Args:
        pred_masks: soft visible masks of all windows (N, H, W).
        pred_depths: (N,).
        active: (N,) bool.
        gt_visible, gt_amodal: (G, H, W) bool.
        gt_boxes: (G, 4) visible boxes, COCO pixels.
        gt_ids: (G,) identity ids.
        threshold: binarisation of the predicted masks.
    """

    s = FrameScore(n_gt=len(gt_ids))
    win = np.flatnonzero(active)
    pm = pred_masks[win] > threshold
    iou = (
        mask_iou(pm, gt_visible) if len(win) and len(gt_ids) else np.zeros((len(win), len(gt_ids)))
    )
    pairs = match(iou)
    pboxes = mask_boxes_xywh(torch.as_tensor(pm)).numpy() if len(win) else np.zeros((0, 4))
    matched_gt = {}
    for p, g in pairs:
        s.iou_sum += iou[p, g]
        s.mask_detected += int(iou[p, g] >= 0.5)
        if box_iou_xywh(pboxes[p : p + 1], gt_boxes[g : g + 1])[0, 0] >= 0.5:
            s.detected += 1
        matched_gt[g] = int(win[p])
        s.matches[int(gt_ids[g])] = int(win[p])
    _score_depth_order(s, pred_depths, gt_visible, gt_amodal, matched_gt)
    G = len(gt_ids)
    H, W = gt_visible.shape[-2:]
    gt_lab = np.full((H, W), -1, np.int64)
    for g in range(G):
        gt_lab[gt_visible[g]] = g
    if len(win):
        weights = pred_masks[win]
        pred_lab = np.where(weights.max(0) > threshold, weights.argmax(0), -1)
    else:
        pred_lab = np.full((H, W), -1)
    if G == 0:
        return s
    s.ari.append(fg_ari(gt_lab, pred_lab))
    _score_merges_and_overlaps(s, pm, gt_visible, gt_amodal, gt_lab, pred_lab, pairs)
    return s


def _score_depth_order(s, pred_depths, gt_visible, gt_amodal, matched_gt) -> None:
    """Depth order over pairs of matched GT individuals whose amodal masks overlap: the one
    more visible in the overlap is in front, and its window must have the smaller depth."""
    G = len(gt_visible)
    for a in range(G):
        for b in range(a + 1, G):
            overlap = gt_amodal[a] & gt_amodal[b]
            if overlap.sum() < MIN_OVERLAP or a not in matched_gt or b not in matched_gt:
                continue
            va, vb = (gt_visible[a] & overlap).sum(), (gt_visible[b] & overlap).sum()
            if va == vb:
                continue
            front, back = (a, b) if va > vb else (b, a)
            s.order_total += 1
            s.order_correct += int(pred_depths[matched_gt[front]] < pred_depths[matched_gt[back]])


def _score_merges_and_overlaps(s, pm, gt_visible, gt_amodal, gt_lab, pred_lab, pairs) -> None:
    """Merged subjects (one window covering half of two) and who owns amodal overlaps."""
    G, n_win = len(gt_visible), len(pm)
    gt_area = gt_visible.reshape(G, -1).sum(1)
    if (gt_area > 0).sum() >= 2:
        s.multi += 1
        if n_win:
            inter = pm.reshape(n_win, -1).astype(np.int64) @ gt_visible.reshape(G, -1).T
            covered = inter >= 0.5 * np.maximum(gt_area, 1)[None]
            s.merged += int((covered.sum(1) >= 2).any())
    in_overlap = (gt_amodal.sum(0) >= 2) & (gt_lab >= 0)
    s.overlap_pixels += int(in_overlap.sum())
    if n_win and in_overlap.any():
        owner = np.full(G, -2)  # row of pred_lab's window per GT individual (-2: unmatched)
        for p, g in pairs:
            owner[g] = p
        s.overlap_owned += int((pred_lab[in_overlap] == owner[gt_lab[in_overlap]]).sum())


def coco_ap(gt_coco, results: list[dict], image_ids: Sequence[int]) -> dict[str, float]:
    """Class-agnostic COCO AP / AP50 for bbox and segm results on ``image_ids``."""

    out = {}
    for iou_type in ("bbox", "segm"):
        if not results:
            out[f"coco_{iou_type}_ap"] = 0.0
            out[f"coco_{iou_type}_ap50"] = 0.0
            continue
        with contextlib.redirect_stdout(io.StringIO()):
            dt = gt_coco.loadRes(results)
            ev = COCOeval(gt_coco, dt, iou_type)
            ev.params.imgIds = list(image_ids)
            ev.params.useCats = 0
            # without categories COCOeval still pools only the results whose category the
            # ground truth lists: a scene of quadrupeds alone (category 2) scored every
            # subject result (category 1) as missing, AP 0, until 2026-12-01
            ev.params.catIds = sorted(set(gt_coco.getCatIds())
                                      | {int(r["category_id"]) for r in results})
            ev.evaluate()
            ev.accumulate()
            ev.summarize()
        out[f"coco_{iou_type}_ap"] = float(max(ev.stats[0], 0.0))
        out[f"coco_{iou_type}_ap50"] = float(max(ev.stats[1], 0.0))
    return out


@torch.no_grad()
def evaluate_model(
    model,
    data,
    frames: Sequence[int],
    gt=None,
    threshold: float = 0.5,
    refine: str = "residual",
    inference=None,
) -> dict[str, float]:
    """All metrics on ``frames`` of ``data`` (an :class:`nsd.io.scene_data.SceneData`).

    Without ground truth only the self-supervised novel-view PSNR/SSIM is returned.
    With it, ``mask_miou_raw`` also scores the compositor's raw masks (no refinement),
    and the metrics of :data:`SPLIT_METRICS` come again as ``<metric>_apart`` and
    ``<metric>_touching`` (:mod:`nsd.evaluation.contact`), with ``touching_share``, the
    share of touching instants. ``inference``: :class:`nsd.inference.multiview.InferenceSettings`
    (None: the defaults, multi-view inference).
    """
    settings = inference or InferenceSettings.defaults()
    was = model.training
    model.eval()
    V = data.num_views
    grid = (
        settings.grid(data.rig, data.frame_hw) if settings.multiview and gt is not None else None
    )
    psnr, ssim = [], []
    tally = Tally()
    # the hull's clustering through the frames in order, the mixture decided for the scene
    track = (ClusterTrack(rules=settings.mixture) if grid is None
             else model_scene_track(model, data.views, frames, grid, settings.mixture))
    try:
        for t in frames:
            views, bgs = data.views(int(t))
            p, s = _novel_view_scores(model, data, views, bgs)
            psnr.append(p)
            ssim.append(s)
            if gt is None:
                continue
            dec = decompose_views(
                model, views, bgs, V, settings, grid, mask_threshold=threshold, refine=refine,
                track=track,
            )
            truths = instant_truth(gt, data, int(t))
            counts = tally.counts(touches(truths))
            per_view = score_views(dec, truths, threshold, counts)
            tally.add_coco(dec, truths, threshold)
            _count_associations(model, dec, data, settings, per_view, counts)
    finally:
        model.train(was)
    out = {"nvs_psnr": float(np.mean(psnr)) if psnr else float("nan"),  # no frames: NaN
           "nvs_ssim": float(np.mean(ssim)) if ssim else float("nan")}
    if gt is not None:
        out.update(tally.metrics())
        out.update(coco_ap(gt.coco, tally.results, tally.image_ids))
    return {k: float(v) for k, v in out.items()}  # plain floats (numpy scalars break JSON)


def _ratio(num: float, den: float) -> float:
    return num / den if den else float("nan")


@dataclass
class Counts:
    """What :func:`evaluate_model` sums over the camera-frames of one part of the instants."""

    total: FrameScore = field(default_factory=FrameScore)
    raw_iou: float = 0.0
    assoc_total: int = 0
    assoc_correct: int = 0
    instants: int = 0

    def metrics(self) -> dict[str, float]:
        total = self.total
        return {
            "detection_rate": _ratio(total.detected, total.n_gt),
            "mask_detection_rate": _ratio(total.mask_detected, total.n_gt),
            "mask_miou": _ratio(total.iou_sum, total.n_gt),
            "mask_miou_raw": _ratio(self.raw_iou, total.n_gt),
            "fg_ari": float(np.nanmean(total.ari)) if total.ari else float("nan"),
            "depth_order_accuracy": _ratio(total.order_correct, total.order_total),
            "depth_order_pairs": float(total.order_total),
            "merge_rate": _ratio(total.merged, total.multi),
            "overlap_ownership": _ratio(total.overlap_owned, total.overlap_pixels),
            "association_accuracy": _ratio(self.assoc_correct, self.assoc_total),
        }


SPLIT_METRICS = (
    "detection_rate",
    "mask_detection_rate",
    "mask_miou",
    "mask_miou_raw",
    "depth_order_accuracy",
    "association_accuracy",
    "merge_rate",
)


@dataclass
class Tally:
    """:class:`Counts` of all instants and of the apart and touching ones, and COCO results."""

    parts: dict[str, Counts] = field(
        default_factory=lambda: {p: Counts() for p in ("all", *PARTS)}
    )
    results: list[dict] = field(default_factory=list)
    image_ids: list[int] = field(default_factory=list)

    def counts(self, touching: bool) -> list[Counts]:
        """The counts an instant adds to: all, and its part (one instant counted)."""
        counts = [self.parts["all"], self.parts[PARTS[int(bool(touching))]]]
        for c in counts:
            c.instants += 1
        return counts

    def add_coco(self, dec, truths: Sequence, threshold: float) -> None:
        """COCO results of every view of one instant (for :func:`coco_ap`); ``truths`` as
        :func:`score_views`."""
        for v, fgt in enumerate(truths):
            self.results += decomposition_to_coco(dec, v, fgt.image_id, fgt.native_size, threshold)
            self.image_ids.append(fgt.image_id)

    def metrics(self) -> dict[str, float]:
        out = self.parts["all"].metrics()
        for part in PARTS:
            m = self.parts[part].metrics()
            out.update({f"{k}_{part}": m[k] for k in SPLIT_METRICS})
        out["touching_share"] = _ratio(self.parts["touching"].instants, self.parts["all"].instants)
        return out


def _novel_view_scores(model, data, views: Tensor, bgs: Tensor) -> tuple[float, float]:
    """Novel-view PSNR and SSIM of one instant: every view re-synthesised from the next."""
    V = data.num_views
    w_idx = (torch.arange(V) + 1) % V
    rv, _, _, _ = call_on_device(
        model, model, views, views[w_idx], bgs, bgs[w_idx], data.rotations[torch.arange(V), w_idx]
    )
    psnr = kornia.metrics.psnr(rv.image.clamp(0, 1), views, 1.0).item()
    ssim = ssim_map(rv.image.clamp(0, 1), views, 7).mean().item()
    return psnr, ssim


def instant_truth(gt, data, t: int) -> list:
    """The ground truth of every view of instant ``t`` at the frames' size: one
    :class:`nsd.io.ground_truth.FrameGT` per camera of ``data``, read once per instant."""
    f = data.frame_index(t)  # positions of a strided scene are not footage frames
    return [gt.frame(cam, f, data.frame_hw) for cam in data.rig.names]


def score_views(dec, truths: Sequence, threshold: float, counts: Sequence[Counts]):
    """Score every view of one instant of a decomposition into each of ``counts``.

    ``dec`` holds per view ``masks`` and ``raw_masks`` (V, N, H, W), ``depths`` and
    ``active`` (V, N) (a :class:`nsd.inference.single.Decomposition`, or the hull-only
    baseline's); ``truths`` the instant's :func:`instant_truth`. Returns each view's GT
    matches (identity -> window).
    """
    per_view = []
    for v, fgt in enumerate(truths):
        truth = (fgt.visible, fgt.amodal, fgt.boxes, fgt.identity, threshold)
        depths, active = np.asarray(dec.depths[v]), np.asarray(dec.active[v])
        s = score_frame(np.asarray(dec.masks[v]), depths, active, *truth)
        raw = score_frame(np.asarray(dec.raw_masks[v]), depths, active, *truth)
        for c in counts:
            c.raw_iou += raw.iou_sum
            c.total.add(s)
        per_view.append(s.matches)
    return per_view


def _count_associations(model, dec, data, settings, per_view, counts: Sequence[Counts]) -> None:
    """Cross-view association: for every GT individual seen in views v and w, is the
    window of w with the highest score for v's window the one matched to it?"""
    V = data.num_views
    for v in range(V):
        for w in range(V):
            if v == w:
                continue
            sim = association_scores(
                model, dec, data.cameras, data.frame_hw, v, w, settings.slot_bonus
            )
            picks = sim.argmax(1).tolist()
            count_associations(per_view[v], per_view[w], picks.__getitem__, counts)


def count_associations(
    matches_v: dict[int, int], matches_w: dict[int, int], pick, counts: Sequence[Counts]
) -> None:
    """Cross-view association of one view pair: for every GT identity matched in both views,
    is ``pick(window in v)`` its window in w?"""
    for ident, iv in matches_v.items():
        if ident in matches_w:
            for c in counts:
                c.assoc_total += 1
                c.assoc_correct += int(pick(iv) == matches_w[ident])
