"""How many individuals the visual hull shows (nsd/cues/count.py), against the truth.

    .venv/bin/python tools/bench_hull_count.py SCENE [SCENE ...] [--report hull_count]

Each scene is an ``nsd-synth`` folder (its ``gt/scene.json`` says how many individuals it
holds and how it was made: the table lists seed, species, cameras and motion, so that the
scenes can be written again); the count is taken as ``nsd-train`` takes it before
training (``SceneData.hull_bodies``: the training size 128 x 128, the default background,
evidence and hull settings, 60 frames spread over the scene). Besides the shipped rule, the
same blobs counted without the top's test (``TOP_DROP`` infinite) and with ``BODY_SHARE``
0.5. Writes ``docs/benchmarks/<report>.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.cues import count  # noqa: E402
from nsd.io.scene_data import SceneData  # noqa: E402
from tools.benchlib import write_report  # noqa: E402

EVIDENCE = (0.02, 0.04)  # conf/loss/default.yaml: evidence_threshold, evidence_softness
RESOLUTION = 48  # conf/prior_proposal/multiview.yaml
BACKGROUND = "modes"  # conf/data/default.yaml


def _made(scene: Path) -> dict[str, object]:
    c = json.loads((scene / "gt" / "scene.json").read_text())["config"]
    rig, motion = c.get("rig", {}), c.get("motion", {})
    return {"individuals": int(c["num_individuals"]), "seed": c.get("seed"),
            "species": "+".join(c.get("species", [])),
            "one_texture": c.get("texture_ids") is not None,
            "cameras": f"{rig.get('count')} {rig.get('kind')}",
            "motion": motion.get("interaction"), "linger": motion.get("linger", 0.0)}


def _variant(data: SceneData, share: float, drop: float) -> int:
    old = count.BODY_SHARE, count.TOP_DROP
    count.BODY_SHARE, count.TOP_DROP = share, drop
    try:
        return data.hull_bodies(*EVIDENCE, RESOLUTION)[0]
    finally:
        count.BODY_SHARE, count.TOP_DROP = old


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--report", default="hull_count")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    for scene in args.scenes:
        data = SceneData(scene, (128, 128), val_fraction=0.0, background=BACKGROUND)
        n, per = data.hull_bodies(*EVIDENCE, RESOLUTION)
        made = _made(scene)
        rows.append({"scene": scene.name, **made, "counted": n,
                     "per_frame": " ".join(str(int(c)) for c in np.bincount(per)),
                     "no_top_test": _variant(data, count.BODY_SHARE, float("inf")),
                     "share_0.5": _variant(data, 0.5, count.TOP_DROP)})
        print(rows[-1], flush=True)
    truth = np.array([r["individuals"] for r in rows])
    summary = {}
    for key in ("counted", "no_top_test", "share_0.5"):
        got = np.array([r[key] for r in rows])
        summary[key] = {"right": int((got == truth).sum()), "more": int((got > truth).sum()),
                        "fewer": int((got < truth).sum()), "scenes": len(rows)}
    notes = (
        "`counted`: the shipped rule (`nsd/cues/count.py`: a blob of the hull's columns is a "
        f"body when its fullest column holds >= {count.BODY_SHARE} of the scene's typical one "
        f"and its top lies <= {count.TOP_DROP} typical columns below the typical top; the "
        f"{count.QUANTILE} quantile of the per-frame counts). `per_frame`: how many of the 60 "
        "frames show 0, 1, 2, ... bodies. `no_top_test`: without the top's test; "
        "`share_0.5`: a blob's fullest column >= 0.5 of the typical one. `nsd-train` warns "
        "before training when footage without a declared count shows more bodies than "
        "`model.num_windows`; a count above the truth would be a false warning.\n\n"
        + "\n".join(f"- **{k}**: right on {v['right']} of {v['scenes']}, more on {v['more']}, "
                    f"fewer on {v['fewer']}" for k, v in summary.items()))
    md, js = write_report(args.report, "How many individuals the visual hull shows", rows,
                          notes, {"summary": summary})
    print(md, js)


if __name__ == "__main__":
    main()
