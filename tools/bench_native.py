"""Visible masks at the footage's native resolution: upsampled against refined at native size.

    .venv/bin/python tools/bench_native.py --checkpoint RUN/train/checkpoint.pt --scene HD_SCENE

A decomposition trained at 128 x 128 on an HD synthetic scene (e.g. ``nsd-synth
image_size=[1280,1024]`` and ``nsd-run``) is exported three times over the same frames
(every ``--step``-th frame of the held-out tail): with ``native_refine=false`` (the
training-size masks upsampled bilinearly and thresholded, the baseline), and with
``native_refine=true`` (``nsd/cues/native.py``), once with the training-size masks' owner
alone (``native_colour=false``) and once with the subjects' colours moving the boundaries
between them (the default); and once more as the default but with the training-size masks
drawn without the individuals' colour models (``inference.colour_model=0``,
:mod:`nsd.inference.colour_models`). Each export is scored against the scene's ground-truth visible
masks at native resolution: every ground-truth instance with at least 16 visible pixels is
matched one-to-one (Hungarian on mask IoU) to the export's masks of its camera-frame;
``miou`` is the mean IoU over ground-truth instances (unmatched: 0), ``boundary_f`` the
F-score of mask boundaries within 2 native pixels (DAVIS-style), both over all instances;
``union_iou`` the IoU of the union of the export's masks with the union of the truth's per
camera-frame (where the foreground is, whoever owns it).

Writes ``docs/benchmarks/<--name>.{md,json}`` (default ``native``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.evaluation.export_masks import export_mask_scores  # noqa: E402
from tools.benchlib import write_report  # noqa: E402


def _made(info: dict) -> str:
    """The ``nsd-synth`` settings of a scene that differ from the default scene's, from its
    ``gt/scene.json``."""
    c = info.get("config", {})
    keys = ("seed", "num_frames", "image_size", "num_individuals", "species", "texture_ids",
            "video")
    out = [f"{k}={json.dumps(c[k]).replace(' ', '')}" for k in keys if k in c]
    rig, motion = c.get("rig", {}), c.get("motion", {})
    out += [f"rig.{k}={json.dumps(rig[k]).replace(' ', '')}" for k in ("kind", "count",
                                                                        "distortion")
            if rig.get(k) is not None]
    out += [f"motion.{k}={motion[k]}" for k in ("interaction", "linger", "area_radius")
            if k in motion]
    return " ".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--step", type=int, default=3, help="every this many held-out frames")
    ap.add_argument("--name", default="native",
                    help="report name: docs/benchmarks/<name>.{md,json} (native_hd for HD)")
    ap.add_argument("--trained", default="`nsd-run train.trainer.max_steps=1000` on it",
                    help="how the checkpoint was made, for the report's note")
    ap.add_argument("--keep", action="store_true",
                    help="keep the exports (a temporary folder, named at the end)")
    args = ap.parse_args()
    scene = Path(args.scene)
    info = json.loads((scene / "gt" / "scene.json").read_text())
    n = info.get("num_frames", 300)
    w, h = info.get("image_size", ["?", "?"])
    start = round(n * 0.8)  # the held-out tail (data.val_fraction 0.2)
    frames = f"{{start: {start}, stop: null, step: {args.step}}}"
    root = Path(tempfile.mkdtemp(prefix="bench-native-"))
    try:
        rows = _rows(args, scene, frames, root)
    finally:  # four exports of every camera-frame: tens of MB each time
        if args.keep:
            print(f"exports kept in {root}", flush=True)
        else:
            shutil.rmtree(root, ignore_errors=True)
    _report(args, scene, info, rows, w, h)


def _rows(args: argparse.Namespace, scene: Path, frames: str, root: Path) -> list[dict]:
    """One row per mask setting: the held-out frames exported into ``root`` and scored."""
    rows = []
    runs = (("upsampled (baseline)", "false", "false", []),
            ("native refine, spatial owner", "true", "false", []),
            ("native refine, colour owner, no colour models at the training size", "true",
             "true", ["inference.colour_model=0"]),
            ("native refine, colour owner (default)", "true", "true", []))
    for label, refine, colour, extra in runs:
        out = root / f"{refine}-{colour}-{len(extra)}"
        t0 = time.perf_counter()
        subprocess.run([str(Path(sys.executable).parent / "nsd-export"),
                        f"checkpoint={args.checkpoint}", f"scene={scene}", f"out={out}",
                        f"frames={frames}", f"native_refine={refine}", f"native_colour={colour}",
                        "views.tensorboard=false", "views.tsne=false", "progress=false",
                        *extra],
                       check=True, capture_output=True)
        seconds = time.perf_counter() - t0
        manifest = json.loads((out / "manifest.json").read_text())
        m = export_mask_scores(out, scene)
        rows.append({"masks": label, "miou": m["native_miou"],
                     "boundary_f": m["native_boundary_f"],
                     "union_iou": m["native_union_iou"],
                     "instances": int(m["native_instances"]),
                     "native_size": "x".join(map(str, next(iter(
                         manifest["scene"]["native_sizes"].values())))),
                     "train_size": "x".join(map(str, manifest["checkpoint"]["image_size"])),
                     "camera_frames": manifest["counts"]["camera_frames"],
                     "export_s": seconds})
        print(rows[-1], flush=True)
    return rows


def _report(args: argparse.Namespace, scene: Path, info: dict, rows: list[dict], w, h) -> None:
    """``docs/benchmarks/<name>.{md,json}``."""
    write_report(
        args.name, f"Visible masks at native resolution ({w} x {h})", rows,
        notes=(f"Scene {scene.name}, checkpoint {Path(args.checkpoint).parent.parent.name}; "
               f"every {args.step}th frame of the held-out tail, every camera. mIoU and "
               "boundary F (2 px) at native resolution against the ground-truth visible "
               "masks, each instance matched one-to-one (unmatched: 0; "
               "nsd/evaluation/export_masks.py). export_s: the whole nsd-export run "
               f"(decoding, model, files). The scene: `nsd-synth {_made(info)}`; the "
               f"checkpoint: {args.trained} (training at the checkpoint's size). "
               "`native_refine=auto`, the export's default, redraws the masks at native "
               "resolution whenever the footage is larger than the training frames."),
    )


if __name__ == "__main__":
    main()
