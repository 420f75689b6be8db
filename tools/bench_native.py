"""Visible masks at the footage's native resolution: upsampled against refined at native size.

    .venv/bin/python tools/bench_native.py --checkpoint RUN/train/checkpoint.pt --scene HD_SCENE

A decomposition trained at 128 x 128 on an HD synthetic scene (e.g. ``nsd-synth
image_size=[512,512]`` and ``nsd-run``) is exported twice over the same frames (every
``--step``-th frame of the held-out tail): with ``native_refine=false`` (the training-size
masks upsampled bilinearly and thresholded, the baseline) and ``native_refine=true``
(``nsd/cues/native.py``). Each export is scored against the scene's ground-truth visible
masks at native resolution: every ground-truth instance with at least 16 visible pixels is
matched one-to-one (Hungarian on mask IoU) to the export's masks of its camera-frame;
``miou`` is the mean IoU over ground-truth instances (unmatched: 0), ``boundary_f`` the
F-score of mask boundaries within 2 native pixels (DAVIS-style), both over all instances.

Writes ``docs/benchmarks/native.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils
from scipy.optimize import linear_sum_assignment

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.benchlib import write_report  # noqa: E402


def _by_image(coco: dict, key: str = "segmentation") -> dict[tuple[str, int], list]:
    images = {im["id"]: im for im in coco["images"]}
    out = defaultdict(list)
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        out[(im["camera"], int(im["frame"]))].append(mask_utils.decode(a[key]).astype(bool))
    return out


def _boundary(m: np.ndarray) -> np.ndarray:
    m8 = m.astype(np.uint8)
    return (m8 - cv2.erode(m8, np.ones((3, 3), np.uint8))) > 0


def _boundary_f(a: np.ndarray, b: np.ndarray, tol: int = 2) -> float:
    ba, bb = _boundary(a), _boundary(b)
    if not ba.any() and not bb.any():
        return 1.0
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tol + 1, 2 * tol + 1))
    da, db = cv2.dilate(ba.astype(np.uint8), k) > 0, cv2.dilate(bb.astype(np.uint8), k) > 0
    precision = (bb & da).sum() / max(bb.sum(), 1)
    recall = (ba & db).sum() / max(ba.sum(), 1)
    return float(2 * precision * recall / max(precision + recall, 1e-9))


def score(export: Path, scene: Path, min_area: int = 16) -> dict[str, float]:
    pred = _by_image(json.loads((export / "subjects.coco.json").read_text()))
    gt_coco = json.loads((scene / "gt" / "coco.json").read_text())
    frames = {k for k in pred} | {
        (im["camera"], int(im["frame"])) for im in json.loads(
            (export / "subjects.coco.json").read_text())["images"]}
    gt = {k: v for k, v in _by_image(gt_coco).items() if k in frames}
    ious, bfs = [], []
    for key, truths in gt.items():
        truths = [t for t in truths if t.sum() >= min_area]
        preds = pred.get(key, [])
        iou = np.zeros((len(truths), len(preds)))
        for i, t in enumerate(truths):
            for j, p in enumerate(preds):
                iou[i, j] = (t & p).sum() / max((t | p).sum(), 1)
        got = dict(zip(*linear_sum_assignment(-iou), strict=True)) if iou.size else {}
        for i, t in enumerate(truths):
            j = got.get(i)
            ious.append(iou[i, j] if j is not None else 0.0)
            bfs.append(_boundary_f(t, preds[j]) if j is not None else 0.0)
    return {"miou": float(np.mean(ious)), "boundary_f": float(np.mean(bfs)),
            "instances": len(ious)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--step", type=int, default=3, help="every this many held-out frames")
    args = ap.parse_args()
    scene = Path(args.scene)
    n = json.loads((scene / "gt" / "scene.json").read_text()).get("num_frames", 300)
    start = round(n * 0.8)  # the held-out tail (data.val_fraction 0.2)
    frames = f"{{start: {start}, stop: null, step: {args.step}}}"
    root = Path(tempfile.mkdtemp(prefix="bench-native-"))
    rows = []
    for label, refine in (("upsampled (baseline)", "false"), ("native refine", "true")):
        out = root / refine
        t0 = time.perf_counter()
        subprocess.run([str(Path(sys.executable).parent / "nsd-export"),
                        f"checkpoint={args.checkpoint}", f"scene={scene}", f"out={out}",
                        f"frames={frames}", f"native_refine={refine}",
                        "views.tensorboard=false", "views.tsne=false", "progress=false"],
                       check=True, capture_output=True)
        seconds = time.perf_counter() - t0
        manifest = json.loads((out / "manifest.json").read_text())
        rows.append({"masks": label, **score(out, scene),
                     "native_size": "x".join(map(str, next(iter(
                         manifest["scene"]["native_sizes"].values())))),
                     "train_size": "x".join(map(str, manifest["checkpoint"]["image_size"])),
                     "camera_frames": manifest["counts"]["camera_frames"],
                     "export_s": seconds})
        print(rows[-1], flush=True)
    write_report(
        "native", "Visible masks at native resolution", rows,
        notes=(f"Scene {scene.name}, checkpoint {Path(args.checkpoint).parent.parent.name}; "
               f"every {args.step}th frame of the held-out tail, every camera. mIoU and "
               "boundary F (2 px) at native resolution against the ground-truth visible "
               "masks, each instance matched one-to-one (unmatched: 0). export_s: the whole "
               "nsd-export run (decoding, model, files)."),
    )


if __name__ == "__main__":
    main()
