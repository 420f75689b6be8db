"""Benchmark of the NeTePu texture stage: colour PSNR and ablations, re-identification, speed.

Writes ``docs/benchmarks/netepu_texture.md`` and ``.json`` (:func:`tools.benchlib.write_report`)
and figures under ``docs/images/``.

Steps (each its own process, so that each can run under the machine's CPU protocol)::

    # texture models on the frozen biped geometry (netepu-train stage=texture)
    .venv/bin/netepu-train stage=texture \\
        init_from=runs/netepu/geometry_biped/checkpoint.pt \\
        trainer.max_minutes=10 trainer.max_steps=0 hydra.run.dir=runs/netepu/texture_full
    ... netepu.texture.model.use_nnopcs=false netepu.texture.model.use_normals=false \\
        hydra.run.dir=runs/netepu/texture_no_nnopcs
    ... netepu.texture.model.local_features=false  hydra.run.dir=runs/netepu/texture_no_local

    .venv/bin/python tools/bench_netepu_texture.py whiten --colour --shrinkage auto \
        --target contrast_w02_normals_colour   # the default re-id whitening into a copy
    .venv/bin/python tools/bench_netepu_texture.py whiten --shrinkage 0.01 \
        --target contrast_w02_normals_whitened  # the same without colour statistics
    .venv/bin/python tools/bench_netepu_texture.py evaluate --baseline-minutes 5
    .venv/bin/python tools/bench_netepu_texture.py speed   # nothing else running
    .venv/bin/python tools/bench_netepu_texture.py report

``evaluate``: for every run, the colour PSNR over all held-out full-map views
(reconstruction and novel pose/view), re-identification rank-1 / mAP of the
held-out codes computed from predicted NNOPCS (and, for comparison, from
ground-truth NNOPCS), then the CNN baseline trained in the same process on the
same training crops (identity + triplet loss) and evaluated on the same
held-out crops; t-SNE + KDE and cluster-separation figures; novel pose/view
synthesis grids. ``speed``: texture-code encodings per second, including
the geometry render, at 128 x 128 and 256 x 256 frames, in two modes:
``frame`` (NeTePu's inference: render the silhouette and NNOPCS of the whole
frame coarse-to-fine, mask the image with the predicted silhouette, encode)
and ``visible mask`` (the pipeline's: the subject's visible mask is given;
NNOPCS is rendered only at the encoder's in-mask crop pixels; the re-identification
embedding, colour statistics included, is computed too).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nsd.synth import LOOK_ALIKE_PAIRS  # noqa: E402
from tools.benchlib import median_time, peak_rss_mb, write_report  # noqa: E402

RUNS = {
    "full": "runs/netepu/texture_full",
    "full_xv": "runs/netepu/texture_full_xv",
    "no_nnopcs": "runs/netepu/texture_no_nnopcs",
    "no_local": "runs/netepu/texture_no_local",
    "contrast_w02_normals": "runs/netepu/texture_w02_normals",
    "contrast_w02_normals_whitened": "runs/netepu/texture_w02_normals_whitened",
    "contrast_hard": "runs/netepu/texture_hard",
    "default_4166_steps": "runs/netepu/texture_long",
    "contrast_w02_normals_colour": "runs/netepu/texture_w02_normals_colour",
}
WORK = ROOT / "runs" / "netepu" / "texture_bench"
IMAGES = ROOT / "docs" / "images"
PAPER = {"full": 19.35, "no_nnopcs": 13.63, "no_local": 14.74}
LOOK_ALIKES = tuple(i for pair in LOOK_ALIKE_PAIRS for i in pair)
TITLES = {
    "texture": "NeTePu texture code (mu, predicted NNOPCS): contours = training cameras, "
    "dots = held-out cameras",
    "baseline": "CNN baseline (identity + triplet): contours = training cameras, "
    "dots = held-out cameras",
    "texture_xv": "NeTePu texture code, cross-view training (mu, predicted NNOPCS): contours = "
    "training cameras, dots = held-out cameras",
    "texture_default": "NeTePu texture code, default (cross-view + contrastive + normals; "
    "whitened [mu, colour statistics], predicted NNOPCS): contours = training cameras, "
    "dots = held-out cameras",
}
ROW_NOTES = {  # what each evaluated run is (netepu-train stage=texture overrides)
    "full": "NeTePu's recipe (reconstruction only)",
    "no_nnopcs": "NeTePu's recipe, RGB-only encoder (use_nnopcs=false)",
    "no_local": "NeTePu's recipe, no per-keypoint texture features (local_features=false)",
    "full_xv": "+ cross-view training (cross_view=0.5)",
    "full_xv_contrast": "+ contrastive codes (contrast_weight=0.05)",
    "contrast_w02_14min": "contrast_weight=0.2, 2083 steps",
    "contrast_w02_textures": "as contrast_w02_14min, every batch a permutation of the 16 "
    "textures (batch_sampling=textures)",
    "contrast_w02_normals": "as contrast_w02_14min, the encoder also reads world normals of the "
    "rendered depth (use_normals=true)",
    "contrast_w02_normals_crop96": "as contrast_w02_normals, 96 x 96 encoder crops (crop_size=96)",
    "contrast_hard": "as contrast_w02_normals, contrast_weight=0.5, contrast_temperature=0.05, "
    "batch_sampling=textures (harder look-alike negatives)",
    "default_4166_steps": "the default recipe (normals, whitening fitted at the end of "
    "training) trained twice as long, 4166 steps",
    "contrast_w02_normals_colour": "contrast_w02_normals, re-identified by the whitening of "
    "[mu, the crop's colour statistics] fitted on 4096 of its training codes, shrinkage chosen "
    "on two folds of training views (`whiten --colour --shrinkage auto`)",
    "contrast_w02_normals_whitened": "contrast_w02_normals with the re-id whitening fitted on "
    "4096 of its training codes (`whiten --shrinkage 0.01`; the default on 2026-11-22 "
    "until the colour statistics): the same codes, "
    "compared as (mu - m) P",
}
DEFAULT_RUN = "contrast_w02_normals_colour"  # conf/netepu/texture/default.yaml's recipe


def _load(run: str):
    from netepu.texture.model import load_texture_model

    return load_texture_model(ROOT / run / "checkpoint.pt")


def _task_for(run: str):
    """Rebuild the run's data and predicted NNOPCS crops (cached) from its config."""
    from netepu.texture.stage import load_texture_task

    return load_texture_task(ROOT / run / "checkpoint.pt")


def _reid(codes: np.ndarray, cameras: np.ndarray, textures: np.ndarray) -> dict[str, float]:
    from nsd.evaluation.reid import nearest_candidates, reid_metrics

    E, T = codes.shape[:2]
    ids = np.tile(np.arange(T), E)
    cams = np.repeat(cameras, T)
    emb = codes.reshape(E * T, -1)
    out = reid_metrics(emb, ids, cams)
    look = np.isin(textures[ids], LOOK_ALIKES)
    top = ids[nearest_candidates(emb, cams[:, None] != cams[None])]
    partner = {a: b for a, b in LOOK_ALIKE_PAIRS} | {b: a for a, b in LOOK_ALIKE_PAIRS}
    wrong = top != ids
    to_partner = np.array(
        [
            partner.get(int(textures[i]), -1) == int(textures[j])
            for i, j in zip(ids, top, strict=True)
        ]
    )
    pairs = {
        f"rank1_pair_{a}_{b}": float((~wrong[np.isin(textures[ids], (a, b))]).mean())
        for a, b in LOOK_ALIKE_PAIRS
    }
    return {
        **out,
        **pairs,
        "rank1_look_alikes": float((~wrong[look]).mean()),
        "rank1_others": float((~wrong[~look]).mean()),
        "errors_to_look_alike_partner": (
            float(to_partner[wrong].mean()) if wrong.any() else float("nan")
        ),
    }


def evaluate(baseline_minutes: float, speed_threads: int = 0, add_only: bool = False) -> None:
    from netepu.reid.baseline import ReidCNN, train_reid_baseline
    from netepu.reid.figures import separation_figure, tsne_kde_figure
    from netepu.texture.evaluation import evaluate_colour, heldout_codes, synthesis_grid
    from nsd.evaluation.reid import reid_metrics

    torch.set_num_threads(1)
    WORK.mkdir(parents=True, exist_ok=True)
    IMAGES.mkdir(parents=True, exist_ok=True)
    results: dict = {"runs": {}}
    keep = {}
    for name, run in RUNS.items():
        if not (ROOT / run / "checkpoint.pt").is_file():
            print(f"skip {name}: no checkpoint")
            continue
        t0 = time.time()
        task, state = _task_for(run)
        codes = task.codes()
        colour = evaluate_colour(task.texture, task.geometry, task.data, codes)
        h = task.data.heldout
        emb = task.reid_embeddings(task.reid_inputs(codes))  # codes when no whitening
        reid = _reid(emb, h["camera"], task.data.textures)
        raw = _reid(codes, h["camera"], task.data.textures)
        reid |= {"mu_rank1": raw["rank1"], "mu_map": raw["map"]}
        E, T = codes.shape[:2]
        euclid = reid_metrics(
            emb.reshape(E * T, -1),
            np.tile(np.arange(T), E),
            np.repeat(h["camera"], T),
            metric="euclidean",
        )
        reid |= {"euclidean_rank1": euclid["rank1"], "euclidean_map": euclid["map"]}
        row = {
            "steps": int(state["step"]),
            "train_minutes": state["train_seconds"] / 60,
            **colour,
            **{f"reid_{k}": v for k, v in reid.items()},
        }
        if task.texture.cfg.use_nnopcs and not task.texture.cfg.use_normals:
            gt = heldout_codes(task.texture, task.data, h["nnopcs"].astype(np.float32))
            row |= {
                f"reid_gt_nnopcs_{k}": v
                for k, v in _reid(gt, h["camera"], task.data.textures).items()
                if k in ("rank1", "map")
            }
        results["runs"][name] = row
        print(name, json.dumps(row), f"{time.time() - t0:.0f}s", flush=True)
        keep[name] = (task, emb, codes)  # retrieval embeddings; codes mu render
    if add_only:  # merge these runs' rows into an existing evaluate.json (no baseline, figures)
        old = json.loads((WORK / "evaluate.json").read_text())
        old["runs"].update(results["runs"])
        (WORK / "evaluate.json").write_text(json.dumps(old, indent=1))
        return
    if "full" not in keep:
        raise SystemExit("no full texture run to evaluate")
    if (WORK / "evaluate.json").is_file():  # keep the rows of runs not evaluated this time
        old = json.loads((WORK / "evaluate.json").read_text())["runs"]
        results["runs"] = {**old, **results["runs"]}
    task, codes, _ = keep["full"]
    data, h = task.data, task.data.heldout
    grid_task, _, grid_codes = keep.get(DEFAULT_RUN, keep.get("full_xv", keep["full"]))
    import cv2

    for held in (False, True):
        grid = synthesis_grid(
            grid_task.texture, grid_task.geometry, data, grid_codes, held, n_targets=3
        )
        name = "netepu_texture_novel_cameras" if held else "netepu_texture_novel_poses"
        cv2.imwrite(
            str(IMAGES / f"{name}.jpg"),
            cv2.cvtColor(grid, cv2.COLOR_RGB2BGR),
            [cv2.IMWRITE_JPEG_QUALITY, 92],
        )
    # baseline: CNN of the texture encoder's size on the masked RGB crops
    tr = data.train
    torch.manual_seed(0)
    enc = task.texture.cfg
    base = ReidCNN(len(data.textures), list(enc.widths), enc.blocks_per_stage, dims=enc.latent)

    def sample(idx: np.ndarray) -> torch.Tensor:
        inside = torch.from_numpy(tr["inside"][tr["sample_view"][idx]])
        rgb = torch.from_numpy(tr["rgb"][idx]).float() / 255
        return torch.cat([rgb, inside[..., None].float()], -1).permute(0, 3, 1, 2)

    fit = train_reid_baseline(
        base, sample, tr["sample_texture"], minutes=baseline_minutes, log=print
    )
    E, T = h["rgb"].shape[:2]
    with torch.no_grad():
        embs = []
        for s in range(0, E * T, 512):
            v, t = np.divmod(np.arange(s, min(E * T, s + 512)), T)
            inside = torch.from_numpy(h["inside"][v])
            rgb = torch.from_numpy(h["rgb"][v, t]).float() / 255
            x = torch.cat([rgb, inside[..., None].float()], -1).permute(0, 3, 1, 2)
            embs.append(base(x)[0])
        base_codes = torch.cat(embs).reshape(E, T, -1).numpy()
    results["baseline"] = {
        **{f"reid_{k}": v for k, v in _reid(base_codes, h["camera"], data.textures).items()},
        "steps": fit["steps"],
        "train_minutes": fit["minutes"],
        "parameters": sum(p.numel() for p in base.parameters()),
        "texture_encoder_parameters": sum(p.numel() for p in task.texture.encoder.parameters()),
    }
    print("baseline", json.dumps(results["baseline"]), flush=True)
    # the same post-hoc whitening as the texture model's, fitted on the baseline's training
    # embeddings, so that the comparison does not credit the whitening to the texture code
    from netepu.texture.embedding import within_class_whitening

    idx = task.spaced_training_samples(4096)
    with torch.no_grad():
        train_emb = torch.cat([base(sample(idx[s : s + 512]))[0] for s in range(0, len(idx), 512)])
    m, proj = within_class_whitening(train_emb.numpy(), tr["sample_texture"][idx], 0.01)
    white = ((base_codes.reshape(E * T, -1) - m) @ proj).reshape(E, T, -1)
    results["baseline_whitened"] = {
        f"reid_{k}": v for k, v in _reid(white, h["camera"], data.textures).items()
    }
    print("baseline whitened", json.dumps(results["baseline_whitened"]), flush=True)
    # and the default's re-id input: [embedding, the crop's colour statistics], the shrinkage
    # chosen on two folds of training views, as TextureTask.fit_reid_whitening does
    from netepu.texture.embedding import colour_statistics, select_shrinkage

    def stats(rgb: np.ndarray, inside: np.ndarray) -> np.ndarray:
        return colour_statistics(torch.from_numpy(rgb).float() / 255, torch.from_numpy(inside))

    views = tr["sample_view"][idx]
    train_u = np.concatenate([train_emb.numpy(), stats(tr["rgb"][idx], tr["inside"][views])], 1)
    held_in = np.repeat(h["inside"][:, None], T, 1).reshape(E * T, *h["inside"].shape[1:])
    held_rgb = h["rgb"].reshape(E * T, *h["rgb"].shape[2:])
    held_u = np.concatenate([base_codes.reshape(E * T, -1), stats(held_rgb, held_in)], 1)
    labels = tr["sample_texture"][idx]
    shrinkage, _ = select_shrinkage(train_u, labels, tr["camera"][views], views)
    m, proj = within_class_whitening(train_u, labels, shrinkage)
    white = ((held_u - m) @ proj).reshape(E, T, -1)
    results["baseline_colour"] = {
        f"reid_{k}": v for k, v in _reid(white, h["camera"], data.textures).items()
    } | {"shrinkage": shrinkage}
    print("baseline with colour statistics", json.dumps(results["baseline_colour"]), flush=True)
    # figures: t-SNE + KDE (contours: training cameras, dots: held-out cameras), separation
    ids = np.tile(np.arange(T), E)
    cams = np.repeat(h["camera"], T)
    dots = np.repeat(h["heldout_camera"], T)
    names = {i: str(int(t)) for i, t in enumerate(data.textures)}
    figs = [("texture", codes), ("baseline", base_codes)]
    sep = {"texture code": (codes.reshape(E * T, -1), ids, cams)}
    if DEFAULT_RUN in keep:
        figs.append(("texture_default", keep[DEFAULT_RUN][1]))
        sep["texture code, default"] = (keep[DEFAULT_RUN][1].reshape(E * T, -1), ids, cams)
    sep["CNN baseline"] = (base_codes.reshape(E * T, -1), ids, cams)
    for label, emb in figs:
        tsne_kde_figure(
            emb.reshape(E * T, -1),
            ids,
            dots,
            IMAGES / f"netepu_reid_tsne_{label}.png",
            TITLES[label],
            names,
        )
    results["separation"] = separation_figure(sep, IMAGES / "netepu_reid_separation.png")
    if speed_threads:
        results["speed_shared_slot"] = _speed_rows(RUNS["full"], repeats=3, threads=speed_threads)
    results["peak_rss_mb"] = peak_rss_mb()
    results["heldout"] = {
        "poses": int(h["pose"].max() + 1),
        "views": int(E),
        "textures": int(T),
        "training_samples": len(tr["sample_view"]),
        "training_views": len(tr["camera"]),
    }
    (WORK / "evaluate.json").write_text(json.dumps(results, indent=1))


def _speed_fns(texture, geometry, image, mask, kps, cam, size: int) -> dict:
    """The two ways of encoding a batch of frames, as callables (see the module docstring)."""
    from netepu.geometry.maps import MapSettings, render_maps
    from netepu.texture.encoding import encode_texture, surface_normals, texture_codes

    def visible_mode():  # the code and its re-id embedding, as netepu-embed writes them
        mu, rgb, inside, _ = texture_codes(
            texture, geometry, image, mask, kps, cam, return_crops=True
        )
        texture.reid_embedding(mu, rgb, inside)

    def frame_mode():
        with torch.no_grad():
            code = geometry.encode(kps)
            ctx = geometry.prepare(code, cam, keypoints=kps)
            maps = render_maps(geometry.query, ctx, (size, size), MapSettings.defaults())
            surface = maps.nnopcs
            if texture.cfg.use_normals:  # world normals of the depth map, in the silhouettes' box
                sil = maps.silhouette
                rows, cols = sil.any(0).any(1).nonzero(), sil.any(0).any(0).nonzero()
                y0, y1 = int(rows.min()), int(rows.max()) + 1
                x0, x1 = int(cols.min()), int(cols.max()) + 1
                ys, xs = torch.meshgrid(
                    torch.arange(y0, y1, dtype=torch.float32),
                    torch.arange(x0, x1, dtype=torch.float32),
                    indexing="ij",
                )
                uv = torch.stack([xs, ys], -1).expand(len(kps), -1, -1, -1)
                n = torch.zeros_like(surface)
                n[:, y0:y1, x0:x1] = surface_normals(
                    maps.depth[:, y0:y1, x0:x1], uv, sil[:, y0:y1, x0:x1], cam.K, cam.R
                )
                surface = torch.cat([surface, n], -1)
        encode_texture(texture, image, maps.silhouette, surface)

    return {"visible mask (pipeline)": visible_mode, "full frame render (NeTePu)": frame_mode}


def _speed_rows(run: str, repeats: int, threads: int) -> list[dict]:
    from nsd.synth import make_individual, make_rig, render_views, sample_pose

    torch.set_num_threads(threads)
    texture, geometry, config = _load(run)
    geo = config["netepu"]["data"]
    ind = make_individual(
        geo["species"],
        identity=geo["identity"],
        seed=geo["seed"],
        proportion_variation=geo["proportion_variation"],
    )
    rng = np.random.default_rng(5)
    rows = []
    for size in (128, 256):
        rig = make_rig("nepumoo", (size, size))
        cams = rig.stacked(torch.float32)
        pose = sample_pose(ind, rng, 1.0)
        r = render_views([ind], [pose], rig, background=True)
        keep = r["visible"][:, 0].flatten(1).any(1)
        views = torch.nonzero(keep).flatten()[:8]
        image = r["rgb"][views]
        mask = r["visible"][views, 0]
        kps = r["keypoints3d"][0].float()[None].expand(len(views), -1, -1)
        cam = cams[views]
        for batch in (1, 8):
            sl = slice(0, batch)
            c = {k: v[sl] for k, v in cam.items()}
            fns = _speed_fns(texture, geometry, image[sl], mask[sl], kps[sl], c, size)
            for mode, fn in fns.items():
                t = median_time(fn, repeats=repeats, warmup=1)
                rows.append(
                    {
                        "frame": f"{size}x{size}",
                        "mode": mode,
                        "batch": batch,
                        "threads": threads,
                        "ms_per_call": 1000 * t,
                        "encodings_per_s": batch / t,
                    }
                )
                print(rows[-1], flush=True)
    return rows


SPEED_MODELS = {  # the speed table's models: NeTePu's recipe and the shipped default
    "full (NNOPCS)": RUNS["full"],
    "default (NNOPCS + normals)": RUNS[DEFAULT_RUN],
}


def speed(repeats: int) -> None:
    rows = []
    for label, run in SPEED_MODELS.items():
        rows += [{"model": label, **r} for r in _speed_rows(run, repeats, threads=2)]
    WORK.mkdir(parents=True, exist_ok=True)
    (WORK / "speed.json").write_text(json.dumps({"rows": rows, "threads": 2}, indent=1))


def _fmt_db(x):
    return round(float(x), 2)


def _r4(x):
    return "" if x is None else round(x, 4)


def report() -> None:
    ev = json.loads((WORK / "evaluate.json").read_text())
    sp = json.loads((WORK / "speed.json").read_text()) if (WORK / "speed.json").is_file() else None
    rows = []
    for name, r in ev["runs"].items():
        rows.append(
            {
                "model": name,
                "PSNR held-out poses (dB)": _fmt_db(r["heldout_poses/psnr_reconstruction"]),
                "PSNR held-out cameras (dB)": _fmt_db(r["heldout_cameras/psnr_reconstruction"]),
                "PSNR novel pose+view, held-out poses": _fmt_db(r["heldout_poses/psnr_novel"]),
                "PSNR novel pose+view, held-out cameras": _fmt_db(r["heldout_cameras/psnr_novel"]),
                "paper PSNR (dB)": PAPER.get(name, ""),
                "re-id rank-1": round(r["reid_rank1"], 4),
                "re-id mAP": round(r["reid_map"], 4),
                "rank-1 look-alike queries": round(r["reid_rank1_look_alikes"], 4),
                "rank-1 other queries": _r4(r.get("reid_rank1_others")),
                "errors to the look-alike partner": _r4(r.get("reid_errors_to_look_alike_partner")),
                "rank-1 / mAP of mu (no whitening)": (
                    f"{r['reid_mu_rank1']:.4f} / {r['reid_mu_map']:.4f}"
                    if "reid_mu_rank1" in r
                    else ""
                ),
                "steps": r["steps"],
                "train min": round(r["train_minutes"], 1),
            }
        )
    b = ev["baseline"]
    baselines = [("CNN baseline (identity + triplet)", b)]
    if ev.get("baseline_whitened"):
        label = "CNN baseline, whitened (the texture model's re-id whitening)"
        baselines.append((label, ev["baseline_whitened"]))
    if ev.get("baseline_colour"):
        label = "CNN baseline with colour statistics, whitened (the default's re-id input)"
        baselines.append((label, ev["baseline_colour"]))
    for label, r in baselines:
        rows.append(
            {
                "model": label,
                "re-id rank-1": round(r["reid_rank1"], 4),
                "re-id mAP": round(r["reid_map"], 4),
                "rank-1 look-alike queries": round(r["reid_rank1_look_alikes"], 4),
                "rank-1 other queries": _r4(r.get("reid_rank1_others")),
                "errors to the look-alike partner": _r4(r.get("reid_errors_to_look_alike_partner")),
                **(
                    {"steps": int(r["steps"]), "train min": round(r["train_minutes"], 1)}
                    if "steps" in r
                    else {}
                ),
            }
        )
    notes = ["Rows:\n"]
    notes += [f"* `{k}`: {ROW_NOTES.get(k, '')}" for k in ev["runs"]]
    notes.append(
        "\nEach row was evaluated when its run was added (`evaluate`, `evaluate --add-only`); "
        "the stamp above is this report's. The speed table comes from the last `speed` run, "
        "both models timed in the same process.\n"
    )
    if sp:
        notes.append(
            "Texture-code encodings per second, geometry render included, 2 threads "
            "(nothing else running):\n"
        )
    elif ev.get("speed_shared_slot"):
        sp = {"rows": ev["speed_shared_slot"]}
        notes.append(
            "Texture-code encodings per second, geometry render included, measured in "
            "the evaluation process with **1 thread on one core while the other core ran "
            "other jobs** (the exclusive 2-core measurement could not be scheduled "
            "before the deadline):\n"
        )
    if sp:
        notes.append(
            "| model | frame | mode | batch | ms per call | encodings/s |\n"
            "|---|---|---|---|---|---|"
        )
        for r in sp["rows"]:
            notes.append(
                f"| {r.get('model', 'full (NNOPCS)')} | {r['frame']} | {r['mode']} "
                f"| {r['batch']} | {r['ms_per_call']:.1f} | {r['encodings_per_s']:.1f} |"
            )
        notes.append("")
    full = ev["runs"].get("full", {})
    if "reid_gt_nnopcs_rank1" in full:
        notes.append(
            f"Re-id of the full model with ground-truth instead of predicted NNOPCS "
            f"crops: rank-1 {full['reid_gt_nnopcs_rank1']:.4f}, mAP "
            f"{full['reid_gt_nnopcs_map']:.4f}.\n"
        )
    notes.append(f"Cluster separation: {json.dumps(ev['separation'])}.\n")
    notes.append(
        f"Held-out set: {json.dumps(ev['heldout'])}; baseline parameters "
        f"{b['parameters']}, texture encoder parameters "
        f"{b['texture_encoder_parameters']}."
    )
    write_report(
        "netepu_texture",
        "NeTePu texture stage: colour PSNR, ablations, re-id, speed",
        rows,
        notes="\n".join(notes),
        extra={"evaluate": ev, "speed": sp},
    )


def whiten(source: str, target: str, samples: int, shrinkage: float | str, colour: bool) -> None:
    """Copy a run's checkpoint to ``target`` and fit the re-id whitening into the copy
    (``colour``: with the crops' colour statistics)."""
    import shutil

    from netepu.texture.stage import add_reid_whitening

    out = ROOT / target
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(ROOT / source / "checkpoint.pt", out / "checkpoint.pt")
    print(add_reid_whitening(out / "checkpoint.pt", samples, shrinkage, colour))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["evaluate", "speed", "report", "whiten"])
    p.add_argument("--baseline-minutes", type=float, default=5.0)
    p.add_argument(
        "--speed-threads",
        type=int,
        default=0,
        help="evaluate: also time encodings with this many threads (in a slot)",
    )
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument(
        "--add-only",
        action="store_true",
        help="evaluate: add the runs' rows to an existing evaluate.json",
    )
    p.add_argument("--run", action="append", default=[], help="name=run folder (replaces RUNS)")
    p.add_argument("--work", default=None, help="folder of the intermediate JSON files")
    p.add_argument("--samples", type=int, default=4096, help="whiten: training codes")
    p.add_argument("--shrinkage", default="0.01", help="whiten: shrinkage (a number or auto)")
    p.add_argument(
        "--colour", action="store_true", help="whiten: with the crops' colour statistics"
    )
    p.add_argument("--source", default="contrast_w02_normals", help="whiten: the run to copy")
    p.add_argument("--target", default=DEFAULT_RUN, help="whiten: the run written (a RUNS name)")
    p.add_argument("--images", default=None, help="figure folder (default docs/images)")
    a = p.parse_args()
    global WORK, IMAGES
    if a.run:
        RUNS.clear()
        RUNS.update(dict(r.split("=", 1) for r in a.run))
    WORK = Path(a.work) if a.work else WORK
    IMAGES = Path(a.images) if a.images else IMAGES
    if a.what == "evaluate":
        evaluate(a.baseline_minutes, a.speed_threads, a.add_only)
    elif a.what == "speed":
        speed(a.repeats)
    elif a.what == "whiten":  # the default run from the run it was fitted on
        shrinkage = a.shrinkage if a.shrinkage == "auto" else float(a.shrinkage)
        whiten(RUNS[a.source], RUNS[a.target], a.samples, shrinkage, a.colour)
    else:
        report()


if __name__ == "__main__":
    main()
