"""How well texture codes tell individuals apart, and the identities each method gives.

    .venv/bin/python tools/bench_code_separation.py --runs ROOT/run1-0 ROOT/run9-0 ... \
        --scenes ROOT/scene1 ROOT/scene9 ...                # ~1 minute, no training

For finished ``nsd-run`` folders with a texture stage (one row per run and species: a run of
two species has one table of codes per species, of which the rows the keypoints stage gave
that species count, as in the identities stage), reads the stored texture codes and gives:

* ``separation``: :func:`netepu.reid.identities.code_separation` (the two closest subjects
  of a frame against what one subject's code moves over 25 frames), the figure by
  which ``netepu.identities.method=auto`` chooses (``SEPARATION_MIN``);
* ``chosen``: the method ``auto`` takes there;
* identity accuracy (all instants / touching instants, against the scene's ground truth,
  :func:`nsd.evaluation.identity.identity_accuracy_by_contact`) of the same rows under
  ``subjects`` (the codes decide, per subject-frame), ``tracks`` (each row its track's
  cluster) and ``motion`` (no codes: the trajectories of the subjects' world positions,
  triangulated from the export's masks, with ``jump`` auto), so that the choice can be
  checked against what each method would have given;
* ``app_separation``: the same figure from NSD's appearance vectors of the same rows (every
  frame has them; ``auto`` does not choose by them).

``--runs`` and ``--scenes`` pair up in order. Writes
``docs/benchmarks/<--report>.{md,json}`` (default ``code_separation``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from netepu.pipeline.species_choice import read_species_csv, species_of_rows
from netepu.reid.identities import (
    SEPARATION_MIN,
    assign_identities,
    auto_method,
    code_separation,
    subject_frames,
)
from nsd.cameras.calibration_io import read_calibration
from nsd.evaluation.identity import identity_accuracy_by_contact
from nsd.export.positions import triangulate_positions
from nsd.inference.multiview import InferenceSettings
from nsd.inference.tracking import position_scale
from nsd.io.embeddings import read_embeddings
from nsd.ops.vectors import unit_vectors
from tools.benchlib import write_report

KEYS = ["id", "camera", "frame", "subject_id"]
COLUMN = "texture_reid"


def _separation(table: dict, column: str = COLUMN) -> float:
    """``code_separation`` of a table's coded subject-frames (codes pooled over the cameras,
    as ``assign_identities`` pools them)."""
    codes = np.asarray(table[column], np.float64)
    ok = ~np.isnan(codes).any(1)
    items, _, pooled = subject_frames(unit_vectors(codes[ok], eps=1e-12),
                                      np.asarray(table["frame"])[ok],
                                      np.asarray(table["subject_id"])[ok])
    return code_separation(pooled, items[:, 0], items[:, 1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="nsd-run folders")
    ap.add_argument("--scenes", type=Path, nargs="+", required=True,
                    help="each run's synthetic scene (its ground truth), in the same order")
    ap.add_argument("--report", default="code_separation")
    args = ap.parse_args()
    if len(args.runs) != len(args.scenes):
        raise SystemExit("--runs and --scenes must pair up: give one scene per run")
    rows = []
    for run, scene in zip(args.runs, args.scenes, strict=True):
        tex = run / "texture"
        rig = read_calibration(scene)
        positions = {key: p for key, (p, _) in triangulate_positions(run / "export", rig).items()}
        jump = position_scale("auto", rig, InferenceSettings.defaults().resolution)
        tables = sorted(d for d in tex.iterdir() if (d / "embeddings.parquet").is_file()) or [tex]
        for folder in tables:
            table = read_embeddings(folder, [*KEYS, COLUMN])
            if folder != tex:  # a species' table: the rows of that species, as the stage
                choices = read_species_csv(run / "keypoints" / "species.csv")
                mine = species_of_rows(table["subject_id"], table["frame"], choices) == \
                    folder.name
                table = {k: np.asarray(v)[mine] for k, v in table.items()}
            sep = _separation(table)
            row = {"run": run.name, "scene": scene.name,
                   "species": folder.name if folder != tex else "", "separation": sep,
                   "chosen": auto_method(sep)}
            for method in ("subjects", "tracks", "motion"):
                identity, _ = assign_identities(table, COLUMN, 0, method, positions=positions,
                                                jump=jump)
                keep = identity >= 0
                acc = identity_accuracy_by_contact(
                    run / "export", scene, {k: np.asarray(v)[keep] for k, v in table.items()},
                    identity[keep], (128, 128))
                row[f"identity_{method}"] = acc.get("identity_accuracy")
                row[f"identity_{method}_touching"] = acc.get("identity_accuracy_touching")
            export = read_embeddings(run / "export", [*KEYS, "app"])
            if folder != tex:
                export = {k: np.asarray(v)[np.isin(export["id"], table["id"])]
                          for k, v in export.items()}
            row["app_separation"] = _separation(export, "app")
            rows.append(row)
            print(row, flush=True)
    write_report(
        args.report, "Texture codes: do they tell the individuals apart?", rows,
        notes=("One row per run and species (the texture stage's table of codes). "
               "`separation`: the median over frames of the cosine distance between the two "
               "closest subjects of a frame, over the median cosine distance between one "
               "track's codes 25 frames apart (netepu.reid.identities."
               f"code_separation); `chosen`: what `netepu.identities.method=auto` takes "
               f"(`subjects` from {SEPARATION_MIN:g} up, else `motion`). `identity_subjects`, "
               "`identity_tracks`, `identity_motion`: identity accuracy of the run's rows "
               "under each method, all instants and touching instants "
               "(nsd/evaluation/identity.py), from the stored codes and export of the run "
               "(`motion`: the subject-frames' positions triangulated from the export's "
               "masks, `jump` auto; nothing re-run). "
               "`app_separation`: the same figure from NSD's appearance vectors of the same "
               "rows, which exist on every frame (what identities use without a texture "
               "model; `auto` takes `subjects` there, whatever the figure)."),
    )


if __name__ == "__main__":
    main()
