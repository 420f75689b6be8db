"""Wall time of the whole default pipeline (``nsd-run``), stage by stage, on this machine.

    .venv/bin/python tools/bench_pipeline.py        # ~11 minutes on 2 cores, nothing else running
    .venv/bin/python tools/bench_pipeline.py prior_mask@train.prior_mask=hull \
        --report pipeline_mask_prior               # with overrides, its own report

Runs ``nsd-run``'s default config (the built-in default scene, 10 minutes of
training) into a fresh run folder, then runs it again to time a resume where
every stage is reused. Writes ``docs/benchmarks/pipeline.{md,json}`` with the
seconds of every stage, the total, the peak memory, the evaluation figures and
the identity accuracy of the run (the default scene has ground truth).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tools.benchlib import peak_rss_mb, write_report

EVAL_KEYS = (
    "detection_rate",
    "mask_miou",
    "mask_miou_raw",
    "depth_order_accuracy",
    "association_accuracy",
    "coco_segm_ap",
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("overrides", nargs="*", help="nsd-run overrides (default: none)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--keep", type=Path, default=None,
                    help="a new folder to run in and keep (default: a temporary one, removed)")
    ap.add_argument("--report", default="pipeline",
                    help="report name (a run with overrides beside the default's report)")
    args = ap.parse_args()
    import logging

    import torch

    from netepu.pipeline.run import load_run_config, run_pipeline
    from nsd.core.app import check_command_line

    check_command_line("nsd-run", "run", args.overrides)  # nsd-run's refusal of bad overrides

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    if args.keep is not None and args.keep.exists():
        raise SystemExit(f"--keep: {args.keep} exists; give a new folder")
    root = args.keep or Path(tempfile.mkdtemp(prefix="nsd-bench-pipeline-"))
    try:
        cfg = load_run_config(
            f"out={root / 'run'}",
            "train.trainer.progress=false",
            "+export.progress=false",
            *args.overrides,
        )
        t0 = time.perf_counter()
        results = run_pipeline(cfg)
        total = time.perf_counter() - t0
        t1 = time.perf_counter()
        again = run_pipeline(cfg)
        resume = time.perf_counter() - t1
        assert all(r.skipped for r in again.values())
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    rows = []
    for name, r in results.items():
        status = "skipped: " + str(r.summary["disabled"]) if "disabled" in r.summary else "ran"
        rows.append(
            {
                "stage": name,
                "status": status,
                "seconds": round(r.seconds, 1),
                "share": f"{100 * r.seconds / total:.1f} %",
            }
        )
    rows.append({"stage": "total", "status": "", "seconds": round(total, 1), "share": "100 %"})
    rows.append(
        {
            "stage": "re-run (every stage reused)",
            "status": "",
            "seconds": round(resume, 2),
            "share": "",
        }
    )
    ev = results["evaluate"].summary.get("metrics", {})
    ident = results["identities"].summary
    extra = {
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "training_steps": results["train"].summary.get("steps"),
        **{f"eval_{k}": round(float(ev[k]), 3) for k in EVAL_KEYS if k in ev},
        "identities_column": ident.get("column"),
        **{f"keypoints_{k}": round(float(v), 3)
           for k, v in results["keypoints"].summary.get("accuracy", {}).items()
           if isinstance(v, int | float)},
        "texture_encoded_rows": results["texture"].summary.get("encoded"),
        **{f"quality_{k}": round(float(v), 3)
           for k, v in results["quality"].summary.get("summary", {}).items()
           if isinstance(v, int | float) and "/" not in k},
        **{f"identities_{k}": round(float(v), 3) for k, v in ident.get("accuracy", {}).items()},
        "export": results["export"].summary,
        "overrides": args.overrides,
    }
    notes = (
        "`nsd-run` with its default config: the built-in default scene (2 individuals, 4 "
        "cameras, 300 frames at 128 x 128; `scene` only reads it when it is already in the user "
        "cache, writing it takes about 7 s more), 10 minutes of NSD training (`train`), "
        "evaluation on 30 held-out frames (`evaluate`), the export of all 300 frames with "
        "crops, Parquet embeddings, MOT tracks, TensorBoard projector and t-SNE (`export`), "
        "NeTePu with the built-in biped model (`netepu/pipeline/models/`): label-free 3D "
        "keypoints by inverse rendering of the subjects of every 25th frame (`keypoints`), "
        "their texture codes and NNOPCS maps (`texture`), an identity for every exported row "
        "from the texture codes (`identities`), the label-free quality report (`quality`), "
        "the pose tools' files (`formats`), a video per camera (`overlays`) and 4 image grids "
        f"(`grids`). Torch threads: {args.threads} set here, then the config's `threads` "
        "(0: every core); the export and the keypoints run one worker process per core "
        "(`workers: auto`)."
    )
    title = "nsd-run: wall time of the default pipeline, stage by stage" + (
        f" ({' '.join(args.overrides)})" if args.overrides else "")
    write_report(args.report, title, rows, notes, extra)


if __name__ == "__main__":
    main()
