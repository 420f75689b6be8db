"""nsd-run: a tiny end-to-end run produces an export and grids; re-running does no work."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
import sleap_io as sio
import torch
from pycocotools.coco import COCO

import netepu.pipeline.stages
from netepu.pipeline.run import load_run_config, run_pipeline
from nsd.core.errors import ConfigError
from nsd.synth import tiny_config, write_scene
from tests.conftest import FIXTURES
from tests.nsd.training.test_train import TINY

NO_VIEWS = ["+export.views.tensorboard=false", "+export.views.tsne=false", "+export.progress=false"]


def _cfg(scene, out, *extra):
    return load_run_config(
        f"scene={scene}",
        f"out={out}",
        *[f"train.{o}" for o in TINY],
        "train.trainer.max_steps=4",
        "train.trainer.max_minutes=0",
        "train.trainer.progress=false",
        "train.trainer.checkpoint_every=0",
        "grids.frames=2",
        "grids.size=48",
        *NO_VIEWS,
        *extra,
    )


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """(scene, run folder, results) of one tiny pipeline run on a copy of the tiny scene."""
    root = tmp_path_factory.mktemp("nsd_run")
    scene = shutil.copytree(FIXTURES / "tiny_scene", root / "tiny_scene")
    return scene, root / "run", run_pipeline(_cfg(scene, root / "run"))


def test_tiny_run_then_rerun_does_no_work(tiny_run, monkeypatch):
    tiny_scene, out, res = tiny_run
    assert [n for n, r in res.items() if r.skipped] == ["evaluate", "keypoints", "texture"]
    no_masks = "the scene has no ground-truth masks (gt/dense/)"
    assert res["evaluate"].summary == {"disabled": no_masks}
    assert (out / "train" / "checkpoint.pt").is_file()
    assert not list(out.glob(".train-work-*"))  # the work folder was moved into place
    coco = COCO(str(out / "export" / "subjects.coco.json"))
    assert len(coco.dataset["images"]) == 2 * 4  # 2 cameras x 4 frames
    assert res["export"].summary["subjects"] == len(coco.dataset["annotations"])
    assert json.loads((out / "export" / "manifest.json").read_text())["counts"]["frames"] == 4
    grids = sorted((out / "grids").glob("frame_*.png"))
    assert [g.name for g in grids] == ["frame_000000.png", "frame_000003.png"]
    img = cv2.imread(str(grids[0]))
    # 2 rows (cameras) x 4 panels (input, boxes, masks, depth) of 48 x 36 with 2-pixel gaps
    assert img.shape == (2 + 2 * 38, 2 + 4 * 50, 3)
    record = json.loads((out / "pipeline.json").read_text())
    assert record["train"]["status"] == "ran" and record["evaluate"]["status"] == "disabled"
    assert record["train"]["summary"]["num_windows"] == 2  # the windows trained, said

    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}

    def no_work(*args, **kwargs):
        raise AssertionError("a finished stage was recomputed")

    monkeypatch.setattr(netepu.pipeline.stages, "train", no_work)
    monkeypatch.setattr(netepu.pipeline.stages, "export_subjects", no_work)
    again = run_pipeline(_cfg(tiny_scene, out))
    assert all(r.skipped for r in again.values())
    assert again["export"].summary == res["export"].summary
    changed = [p for p, t in stamps.items() if p.stat().st_mtime_ns != t]
    assert changed == [out / "pipeline.json"]


def test_a_trained_decomposition_is_loaded_instead_of_trained(tiny_run, tmp_path, monkeypatch):
    """checkpoint=<nsd-train checkpoint>: the train stage copies it (no training), and the
    export is the trained run's; a missing file or another kind of checkpoint is an error."""
    from nsd.core.atomic import atomic_save_torch
    from nsd.core.errors import CheckpointError

    tiny_scene, first, _ = tiny_run

    def no_training(*args, **kwargs):
        raise AssertionError("trained although a checkpoint was given")

    monkeypatch.setattr(netepu.pipeline.stages, "train", no_training)
    ckpt = first / "train" / "checkpoint.pt"
    res = run_pipeline(_cfg(tiny_scene, tmp_path / "run", f"checkpoint={ckpt}"))
    assert res["train"].summary["loaded_from"] == str(ckpt)
    assert res["train"].summary["num_windows"] == 2
    assert (tmp_path / "run" / "train" / "checkpoint.pt").read_bytes() == ckpt.read_bytes()
    a = json.loads((first / "export" / "subjects.coco.json").read_text())["annotations"]
    b = json.loads((tmp_path / "run" / "export" / "subjects.coco.json").read_text())["annotations"]
    assert [x["bbox"] for x in a] == [x["bbox"] for x in b]
    with pytest.raises(ConfigError, match="does not exist"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run2", f"checkpoint={tmp_path / 'nope.pt'}"))
    atomic_save_torch({"format": "nsd-netepu-checkpoint-v1", "modules": {}}, tmp_path / "x.pt")
    with pytest.raises(CheckpointError, match="not an NSD decomposition checkpoint"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run3", f"checkpoint={tmp_path / 'x.pt'}"))
    assert not (tmp_path / "run3" / "train").exists()


def test_changed_grid_setting_reruns_only_grids(tiny_run, tmp_path, monkeypatch):
    tiny_scene, first, _ = tiny_run
    out = shutil.copytree(first, tmp_path / "run")
    monkeypatch.setattr(
        netepu.pipeline.stages, "train", lambda *a, **k: pytest.fail("train re-ran")
    )
    res = run_pipeline(_cfg(tiny_scene, out, "grids.frames=1"))
    assert res["train"].skipped and res["export"].skipped and not res["grids"].skipped
    assert [g.name for g in (out / "grids").glob("*.png")] == ["frame_000000.png"]


def test_a_changed_inference_setting_reruns_evaluate_and_export_not_train(tiny_run, tmp_path,
                                                                          monkeypatch):
    """Inference settings (the masks' ownership, ...) change what is made of the checkpoint,
    not the checkpoint: sweeping them never re-trains."""
    tiny_scene, first, _ = tiny_run
    out = shutil.copytree(first, tmp_path / "run")
    monkeypatch.setattr(
        netepu.pipeline.stages, "train", lambda *a, **k: pytest.fail("train re-ran")
    )
    res = run_pipeline(_cfg(tiny_scene, out, "train.inference.hull_contested=0.5"))
    assert res["train"].skipped and not res["export"].skipped
    manifest = json.loads((out / "export" / "manifest.json").read_text())
    assert manifest["config"]["inference"]["hull_contested"] == 0.5


def test_a_changed_shipped_export_default_reruns_the_export(tiny_run, tmp_path, monkeypatch):
    """The export stage is keyed by nsd-export's whole config, not only the run's overrides:
    a toolkit whose conf/export.yaml changed re-exports; where it runs (workers) does not."""
    from nsd.export.config import load_export_config

    tiny_scene, first, _ = tiny_run
    out = shutil.copytree(first, tmp_path / "run")
    monkeypatch.setattr(
        netepu.pipeline.stages, "train", lambda *a, **k: pytest.fail("train re-ran")
    )
    res = run_pipeline(_cfg(tiny_scene, out, "+export.workers=1"))
    assert res["export"].skipped

    def changed(**overrides):
        cfg = load_export_config(**overrides)
        cfg.tracking.min_similarity = 0.31  # as a new release's default would
        return cfg

    monkeypatch.setattr(netepu.pipeline.stages, "load_export_config", changed)
    res = run_pipeline(_cfg(tiny_scene, out))
    assert res["train"].skipped and not res["export"].skipped


def test_missing_scene_is_a_clear_error(tmp_path):
    from nsd.core.errors import NSDError

    with pytest.raises(NSDError, match="nope"):
        run_pipeline(_cfg(tmp_path / "nope", tmp_path / "run"))


def test_unknown_identity_method_fails_before_any_stage(tiny_scene, tmp_path):
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"netepu\.identities\.method"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run", "netepu.identities.method=x"))
    assert not (tmp_path / "run").exists()


def test_switched_off_windows_get_no_export_rows(tmp_path):
    """Upper bound 3 windows, 1 individual: windows whose presence is off are not exported.

    The presence of windows 1 and 2 is switched off in the trained checkpoint (head rows
    zeroed, bias -20: presence ~2e-9 for every input), as a trained model does for windows
    it does not need (docs/benchmarks/count.md measures whether training gets there).
    """
    from nsd.export.config import load_export_config
    from nsd.export.subjects import export_subjects
    from nsd.inference.single import decompose
    from nsd.io.embeddings import read_embeddings
    from nsd.model.checkpoint import load_decomposition

    scene = write_scene(tiny_config(num_individuals=1), tmp_path / "scene")
    out = tmp_path / "run"
    cfg = _cfg(
        scene,
        out,
        "train.data.image_size=[48,48]",
        "train.model.num_windows=3",
        "train.model.detector.presence=true",
        "prior_presence@train.prior_presence=sparse",
        "evaluate.max_frames=2",
    )
    res = run_pipeline(cfg)
    assert res["evaluate"].summary["metrics"]["frames"] == 2.0  # the scene has ground truth
    state = torch.load(out / "train" / "checkpoint.pt", weights_only=True)
    head = state["modules"]["model"]
    w, b = head["detector.head.weight"], head["detector.head.bias"]
    for k in (1, 2):  # the 6 outputs per window: scale (2), position (2), depth, presence
        w[6 * k + 5] = 0.0
        b[6 * k + 5] = -20.0
    ckpt = tmp_path / "off.pt"
    torch.save(state, ckpt)
    trained = load_decomposition(ckpt)
    from nsd.io.scene_data import SceneData

    data = SceneData(scene, (48, 48), val_fraction=0.0)
    dec = decompose(trained.model, *data.views(0))
    assert not dec.active[:, 1:].any()
    assert dec.crops[:, 1:].abs().sum() == 0  # switched-off windows are not even cropped
    ecfg = load_export_config(
        checkpoint=str(ckpt),
        scene=str(scene),
        out=str(tmp_path / "exp"),
        **{"views.tensorboard": False, "views.tsne": False, "progress": False},
    )
    s = export_subjects(ecfg)
    table = read_embeddings(tmp_path / "exp" / "embeddings.parquet")
    slots = set(np.asarray(table["slot"]).tolist())
    assert 0 < s.subjects == len(table["slot"]) and slots == {0}
    anns = json.loads((tmp_path / "exp" / "subjects.coco.json").read_text())["annotations"]
    assert {a["slot"] for a in anns} <= {0} and len(anns) == s.subjects


def test_netepu_stages_with_tiny_models(tmp_path):
    """Keypoints, texture codes and identities with tiny (untrained) NeTePu models: the files
    hold one keypoint set and one code per inverted exported row, identities cover every track."""
    from netepu.geometry.model import build_geometry_model
    from netepu.texture.model import build_texture_model
    from nsd.core.atomic import atomic_save_torch
    from nsd.io.embeddings import read_embeddings
    from tests.netepu.texture.test_texture import K_BIPED, R_BIPED, TINY_GEOMETRY_DATA, TINY_TEXTURE
    from tests.netepu_world import TINY_MODEL

    torch.manual_seed(0)
    geo = build_geometry_model(TINY_MODEL, K_BIPED, R_BIPED)
    tex = build_texture_model(TINY_TEXTURE, geo)
    data = {**TINY_GEOMETRY_DATA, "n_keypoints": K_BIPED}
    netepu = {"model": TINY_MODEL, "data": data, "texture": {"model": TINY_TEXTURE}}
    for name, modules in (
        ("geo.pt", {"geometry": geo}),
        ("tex.pt", {"geometry": geo, "texture": tex}),
    ):
        atomic_save_torch(
            {"format": "nsd-netepu-checkpoint-v1",
             "modules": {k: m.state_dict() for k, m in modules.items()},
             "config": {"netepu": netepu}},
            tmp_path / name,
        )  # fmt: skip
    scene = write_scene(tiny_config(), tmp_path / "scene")
    out = tmp_path / "run"
    res = run_pipeline(
        _cfg(scene, out, "train.data.image_size=[48,48]", "evaluate.max_frames=2",
             f"netepu.geometry={tmp_path / 'geo.pt'}", f"netepu.texture={tmp_path / 'tex.pt'}",
             "netepu.keypoints.frame_step=3", "netepu.keypoints.steps=4",
             "netepu.keypoints.templates=1", "netepu.keypoints.min_area=1")
    )  # fmt: skip
    assert not any(r.skipped for n, r in res.items() if n != "scene")
    export = read_embeddings(out / "export")
    kp = np.load(out / "keypoints" / "keypoints3d.npz")
    assert kp["keypoints"].shape == (len(kp["id"]), K_BIPED, 3) and len(kp["id"]) > 0
    assert set(kp["id"].tolist()) <= set(export["id"].tolist())
    inverted_frames = set(np.asarray(export["frame"])[np.isin(export["id"], kp["id"])].tolist())
    assert inverted_frames <= {0, 3}  # frame_step=3 over 6 frames
    table = read_embeddings(out / "texture")
    assert np.array_equal(table["id"], export["id"])
    valid = table["texture_valid"]
    assert valid.sum() == res["texture"].summary["encoded"] > 0
    assert np.array_equal(valid, np.isin(table["id"], kp["id"]))  # codes need keypoints
    assert table["texture"].shape == (len(table["id"]), TINY_TEXTURE["latent"])
    assert not (out / "texture" / "crops").exists()
    with np.load(out / "texture" / "nnopcs.npz") as z:  # what the encoder read, per coded row
        S = TINY_TEXTURE["crop_size"]
        assert sorted(z["id"].tolist()) == sorted(table["id"][valid].tolist())
        assert z["rgb"].shape == (len(z["id"]), S, S, 3) and z["rgb"].dtype == np.uint8
        assert z["nnopcs"].shape == (len(z["id"]), S, S, 3)
        inside, nnopcs = z["inside"], z["nnopcs"].astype(np.float32)
        assert inside.any() and not nnopcs[~inside].any()
        assert 0 <= nnopcs.min() <= nnopcs.max() <= 1
        assert not z["rgb"][~inside].any()  # masked crops
    assert cv2.imread(str(out / "texture" / "nnopcs.png")) is not None
    head, *lines = (out / "identities" / "identities.csv").read_text().split()
    assert head == "id,camera,frame,subject_id,identity"
    assert [int(r.split(",")[0]) for r in lines] == export["id"].tolist()  # one line per row
    assert [int(r.split(",")[3]) for r in lines] == export["subject_id"].tolist()
    acc = res["identities"].summary["accuracy"]
    assert res["identities"].summary["column"] == "texture_reid"
    assert acc["matched_rows"] == 0 or 0 <= acc["identity_accuracy"] <= 1
    assert res["keypoints"].summary["accuracy"]["inverted"] == len(kp["subject_frame"])


def _track_table(spec, rng, cameras=("a",)):
    """Embedding table of tracks ``(subject_id, frames, code)``, one row per camera and frame."""
    rows = [
        (s, t, cam, c + 0.05 * rng.normal(size=len(c)))
        for s, frames, c in spec
        for t in frames
        for cam in cameras
    ]
    return {
        "id": np.arange(len(rows)),
        "subject_id": np.array([r[0] for r in rows]),
        "frame": np.array([r[1] for r in rows]),
        "camera": np.array([r[2] for r in rows]),
        "texture": np.stack([r[3] for r in rows]),
    }


def _swapped_pair(swap: int, rng) -> tuple[dict, np.ndarray]:
    """Tracks 1 and 2 over frames 0-39, seen by cameras a and b, swapping individuals (codes
    e0, e1) at frame ``swap``; codes on every 10th frame. ``(table, truth)``, truth 0 for
    e0's rows."""
    a, b = np.eye(8)[0], np.eye(8)[1]
    spec = [(1, range(swap), a), (1, range(swap, 40), b), (2, range(swap), b),
            (2, range(swap, 40), a)]
    table = _track_table(spec, rng, cameras=("a", "b"))
    table["texture_valid"] = table["frame"] % 10 == 0
    return table, np.array([0 if c[0] > 0.5 else 1 for c in table["texture"]])


@pytest.mark.parametrize("method", ["subjects", "rows", "tracks"])
def test_identities_join_tracks_of_one_texture_and_keep_co_visible_tracks_apart(method):
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(0)
    a, b = np.eye(8)[0], np.eye(8)[1]
    # tracks 1 and 2 are individual A before and after a break, 3 is B, 4 is B after a break;
    # tracks of different individuals are seen together in more than HANDOVER_FRAMES frames
    spec = [(1, range(20), a), (2, range(24, 40), a), (3, range(30), b), (4, range(32, 40), b)]
    table = _track_table(spec, rng, cameras=("a", "b"))
    identity, summary = assign_identities(table, k=0, method=method)
    assert summary["k"] == 2 and summary["identities"] == 2
    of = {s: set(identity[table["subject_id"] == s].tolist()) for s in (1, 2, 3, 4)}
    assert of[1] == of[2] and of[3] == of[4] and len(of[1]) == 1 and of[1] != of[3]
    # one texture for everyone: individuals seen together still get different identities
    table["texture"] = np.tile(a, (len(identity), 1))
    identity, _ = assign_identities(table, method=method)
    for t in range(40):
        for cam in ("a", "b"):
            here = identity[(table["frame"] == t) & (table["camera"] == cam)]
            assert len(set(here.tolist())) == len(here)
    identity, summary = assign_identities(table, k=1, method=method)
    assert set(identity.tolist()) == {0} and summary["association"] == "skipped: one subject"


def test_a_track_handed_over_a_few_frames_early_joins_its_individual(monkeypatch):
    """Individual A is track 1 until frame 20 and track 2 from frame 17 (the tracker opened
    the new track 4 frames before closing the old); B is track 3 throughout. Seen together
    in 4 frames, tracks 1 and 2 still join: two identities. Never joining tracks seen
    together at all (HANDOVER_FRAMES = 0) leaves three."""
    from netepu.reid import identities

    rng = np.random.default_rng(9)
    a, b = np.eye(8)[0], np.eye(8)[1]
    table = _track_table([(1, range(21), a), (2, range(17, 40), a), (3, range(40), b)], rng)
    identity, summary = identities.assign_identities(table, method="tracks")
    assert summary["identities"] == 2
    assert set(identity[table["subject_id"] == 1]) == set(identity[table["subject_id"] == 2])
    monkeypatch.setattr(identities, "HANDOVER_FRAMES", 0)
    _, summary = identities.assign_identities(table, method="tracks")
    assert summary["identities"] == 3


def test_auto_identities_follow_the_codes_unless_they_cannot_tell_individuals_apart():
    """Two tracks that swap individuals at frame 10. With distinct codes ``auto`` takes
    ``subjects`` and every row follows its code; with one code for both individuals (noise
    alone: the closest subjects of a frame are as far apart as a track's consecutive codes)
    it takes ``tracks``, each track one identity, instead of a coin toss per frame."""
    from netepu.reid.identities import SEPARATION_MIN, assign_identities

    rng = np.random.default_rng(7)
    a, b = np.eye(8)[0], np.eye(8)[1]
    early, late = range(0, 200, 20), range(200, 400, 20)  # coded every 20 frames
    spec = [(1, early, a), (1, late, b), (2, early, b), (2, late, a)]
    table = _track_table(spec, rng, cameras=("a", "b"))
    truth = np.array([0 if c[0] > 0.5 else 1 for c in table["texture"]])
    identity, summary = assign_identities(table, method="auto")
    assert summary["method"] == "subjects" and summary["chosen_by"] == "auto"
    assert summary["separation"] > 10 * SEPARATION_MIN

    def never():  # what motion would need: asked for only where motion is taken
        raise AssertionError("positions decoded although the codes decide")

    _, summary = assign_identities(table, method="auto", positions=never, jump=0.2)
    assert summary["method"] == "subjects"
    assert (identity == truth).all() or (identity == 1 - truth).all()
    table["texture"] = a + 0.05 * rng.normal(size=table["texture"].shape)
    identity, summary = assign_identities(table, method="auto")
    assert summary["method"] == "tracks" and summary["separation"] < SEPARATION_MIN
    of = {s: set(identity[table["subject_id"] == s].tolist()) for s in (1, 2)}
    assert of[1] != of[2] and len(of[1]) == len(of[2]) == 1
    by_subjects, _ = assign_identities(table, method="subjects")  # forced: no track stays whole
    assert max(len(set(by_subjects[table["subject_id"] == s].tolist())) for s in (1, 2)) == 2


def test_motion_identities_follow_where_look_alikes_go_when_their_tracks_swap():
    """Two individuals of one look at x = 0 and x = 1; their tracks swap at frame 100 (one
    frame, frame 100, mixes them: both subjects at x = 0.5). ``tracks`` keeps the swap
    (half the rows wrong), ``motion`` stitches the tracks back by position, and ``auto``
    takes it when it has the positions (``tracks`` without). A subject-frame without a
    position (seen by one camera) takes its track's identity at the nearest frame with one."""
    from netepu.reid.identities import SEPARATION_MIN, assign_identities

    rng = np.random.default_rng(5)
    a = np.eye(8)[0]
    frames = range(0, 200, 4)
    table = _track_table([(1, frames, a), (2, frames, a)], rng, cameras=("a", "b"))
    f, s = table["frame"], table["subject_id"]
    x = np.array([1.0, 0.0, 0.0])
    where = {(t, k): (0.5 if t == 100 else (k - 1 if t < 100 else 2 - k)) * x
             for t in frames for k in (1, 2)}
    positions = {key: p for key, p in where.items() if key != (8, 1)}  # one view only
    truth = np.array([round(where[(t, k)][0]) for t, k in zip(f.tolist(), s.tolist(), strict=True)])
    scored = f != 100
    by_tracks, _ = assign_identities(table, method="tracks")
    assert max((by_tracks == truth)[scored].mean(), (by_tracks != truth)[scored].mean()) < 0.6
    identity, summary = assign_identities(table, method="motion", positions=positions, jump=0.2)
    assert summary["identities"] == 2 and summary["tracklets"] == 6
    assert summary["rows_without_position"] == 0  # frame 8 of track 1: from frames 4 and 12
    assert (identity == truth)[scored].all() or (identity != truth)[scored].all()
    assert len(set(identity[f == 100].tolist())) == 2  # the mixed frame: distinct identities
    identity, summary = assign_identities(table, method="auto", positions=lambda: positions,
                                          jump=0.2)
    assert summary["method"] == "motion" and summary["separation"] < SEPARATION_MIN
    assert (identity == truth)[scored].all() or (identity != truth)[scored].all()
    for none in (None, {}, dict):  # no positions (nobody seen by two cameras): the tracks
        _, summary = assign_identities(table, method="auto", positions=none, jump=0.2)
        assert summary["method"] == "tracks"
    with pytest.raises(ValueError, match="motion needs"):
        assign_identities(table, method="motion")
    with pytest.raises(ValueError, match="motion needs"):
        assign_identities(table, method="motion", positions=positions, jump=0.0)


def test_code_separation_known_values_and_edge_cases():
    from functools import partial

    from netepu.reid import identities

    code_separation = partial(identities.code_separation, gap=1)  # frames 0 and 1 compared
    a, b, c = np.eye(3)
    # frame 0: tracks 1, 2, 3 with codes a, b, (a + b) / sqrt 2: closest pair 1 - 1/sqrt 2
    # frame 1: the same tracks, each code unchanged but track 1's turned to (3a + 4b) / 5
    codes = np.stack([a, b, (a + b) / np.sqrt(2), 0.6 * a + 0.8 * b, b, (a + b) / np.sqrt(2)])
    frame, track = np.array([0, 0, 0, 1, 1, 1]), np.array([1, 2, 3, 1, 2, 3])
    closest_0 = 1 - 1 / np.sqrt(2)
    closest_1 = min(1 - 0.8, 1 - (0.6 + 0.8) / np.sqrt(2), 1 - 1 / np.sqrt(2))
    moved = np.median([1 - 0.6, 0.0, 0.0])  # only track 1 moved: the median is 0
    assert moved == 0 and code_separation(codes, frame, track) == np.inf
    codes[5] = (a + b + 0.2 * c) / np.linalg.norm(a + b + 0.2 * c)  # track 3 moves a little
    moved = np.median([1 - 0.6, 0.0, 1 - codes[2] @ codes[5]])
    expect = np.median([closest_0, min(1 - 0.8, 1 - codes[3] @ codes[5], 1 - codes[4] @ codes[5])])
    assert closest_1 > 0 and code_separation(codes, frame, track) == pytest.approx(expect / moved)
    assert code_separation(np.stack([a, a, a, a]), frame[:4] * 0 + np.array([0, 0, 1, 1]),
                           np.array([1, 2, 1, 2])) == 0.0  # equal codes: nothing told apart
    assert code_separation(codes[:3], frame[:3], track[:3]) == np.inf  # no track coded twice


def test_code_separation_compares_a_tracks_codes_gap_frames_apart():
    """Two subjects of one look on every frame, 0.3 rad apart; each code turns 0.01 rad per
    frame. Neighbouring frames would make them look 900 times apart (1 - cos 0.3 against
    1 - cos 0.01); 25 frames apart, the codes move 0.25 rad and the figure is ~1.4."""
    from netepu.reid.identities import SEPARATION_GAP, SEPARATION_MIN, code_separation

    t = np.arange(100)
    angle = np.concatenate([0.01 * t, 0.01 * t + 0.3])
    codes = np.stack([np.cos(angle), np.sin(angle)], 1)
    frame, track = np.concatenate([t, t]), np.repeat([1, 2], len(t))
    expect = (1 - np.cos(0.3)) / (1 - np.cos(0.01 * SEPARATION_GAP))
    assert code_separation(codes, frame, track) == pytest.approx(expect)
    assert expect < SEPARATION_MIN
    assert code_separation(codes, frame, track, gap=1) == pytest.approx(
        (1 - np.cos(0.3)) / (1 - np.cos(0.01)))


def test_identities_stage_warns_when_the_codes_cannot_tell_individuals_apart(tmp_path, caplog):
    import logging

    from omegaconf import OmegaConf

    from netepu.pipeline.stages import _assign, look_alike
    from nsd.io.embeddings import EmbeddingWriter

    rng = np.random.default_rng(8)
    every_20th = range(0, 240, 20)
    table = _track_table([(1, every_20th, np.eye(8)[0]), (2, every_20th, np.eye(8)[0])], rng,
                         cameras=("cam0", "cam1"))
    w = EmbeddingWriter(tmp_path / "embeddings")
    w.write({"id": table["id"], "camera": table["camera"].astype(object),
             "frame": table["frame"], "subject_id": table["subject_id"],
             "texture_reid": table["texture"].astype(np.float32),
             "app": table["texture"].astype(np.float32)})
    w.close()
    i = OmegaConf.create({"fill": "nearest", "method": "auto", "restarts": 10, "k": 0})
    with caplog.at_level(logging.WARNING):
        _, identity, summary = _assign(tmp_path, None, "texture_reid", i, 0)
    assert summary["method"] == "tracks"
    assert "do not tell the individuals apart" in caplog.text and str(tmp_path) in caplog.text
    assert len(set(identity[table["subject_id"] == 1].tolist())) == 1
    caplog.clear()
    i.method = "subjects"  # asked for: no warning, no choice made
    _, _, summary = _assign(tmp_path, None, "texture_reid", i, 0)
    assert summary["method"] == "subjects" and "separation" not in summary and not caplog.text
    i.method = "auto"  # NSD's appearance vectors (no texture model), nobody seen by two
    _, _, summary = _assign(tmp_path, None, "app", i, 0)  # cameras: the subjects, as before
    assert summary["method"] == "subjects" and "separation" not in summary and not caplog.text
    x = np.array([1.0, 0.0, 0.0])
    motion = (lambda: {(t, k): (k - 1) * x for t in every_20th for k in (1, 2)}, 0.2)
    with caplog.at_level(logging.WARNING):  # with positions: where they go, no look-alike
        _, identity, summary = _assign(tmp_path, None, "app", i, 0, motion)  # warning
    assert summary["method"] == "motion" and "separation" not in summary and not caplog.text
    assert summary["chosen_by"] == "auto: no texture codes" and not look_alike(summary)
    assert len(set(identity[table["subject_id"] == 1].tolist())) == 1
    i.method = "auto"  # with the subjects' positions: from where they go, and said so
    with caplog.at_level(logging.WARNING):
        _, identity, summary = _assign(tmp_path, None, "texture_reid", i, 0, motion)
    assert summary["method"] == "motion" and "where the subjects go" in caplog.text
    assert identity[table["subject_id"] == 1].tolist() == [0] * len(every_20th) * 2
    assert identity[table["subject_id"] == 2].tolist() == [1] * len(every_20th) * 2


def test_row_identities_follow_the_codes_when_tracks_swap_individuals():
    """Two tracks swap individuals at frame 10 (a crossing): each track is one identity under
    ``tracks``, which is then wrong for half the rows; ``rows`` follows every row's code."""
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(1)
    a, b = np.eye(8)[0], np.eye(8)[1]
    spec = [(1, range(10), a), (1, range(10, 20), b), (2, range(10), b), (2, range(10, 20), a)]
    table = _track_table(spec, rng, cameras=("a", "b", "c"))
    truth = np.array([0 if c[0] > 0.5 else 1 for c in table["texture"]])
    by_rows, summary = assign_identities(table, method="rows")
    assert summary["identities"] == 2
    assert (by_rows == truth).all() or (by_rows == 1 - truth).all()
    by_tracks, _ = assign_identities(table, method="tracks")
    assert max((by_tracks == truth).mean(), (by_tracks == 1 - truth).mean()) == 0.5
    with pytest.raises(ValueError, match="method"):
        assign_identities(table, method="frames")


def test_rows_without_a_code_take_their_tracks_identity():
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(2)
    a, b = np.eye(8)[0], np.eye(8)[1]
    table = _track_table([(1, range(0, 12), a), (2, range(0, 12), b), (3, range(12, 14), b)], rng)
    table["texture_valid"] = (table["frame"] % 3 == 0) & (table["subject_id"] != 3)
    identity, summary = assign_identities(table)
    assert summary["tracks"] == 2
    for s in (1, 2):  # every row of a coded track, coded or not, has the track's identity
        assert len(set(identity[table["subject_id"] == s].tolist())) == 1
    assert identity[table["subject_id"] == 1][0] != identity[table["subject_id"] == 2][0]
    assert (identity[table["subject_id"] == 3] == -1).all()  # a track without codes


def test_uncoded_rows_take_their_tracks_identity_at_the_nearest_coded_frame():
    """Codes on every 10th frame; the two tracks swap individuals at frame 14, between the
    coded frames 10 and 20. ``nearest`` gives each uncoded row the identity its track has
    at the nearest coded frame (the earlier one on a tie): wrong only at frames 14 and 15,
    whose nearest coded frame, 10, precedes the swap. ``tracks`` (the track's most frequent
    identity) gives a track's uncoded rows one identity, wrong on one whole side of the swap."""
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(4)
    table, truth = _swapped_pair(14, rng)
    frame = table["frame"]
    # (four coded frames, one pair 25 apart per track, across the swap: too few for
    # method=auto to judge the codes by)
    near, summary = assign_identities(table, method="subjects", fill="nearest")
    assert summary["identities"] == 2
    if (near[frame == 0] != truth[frame == 0]).any():
        truth = 1 - truth
    assert set(frame[near != truth].tolist()) == {14, 15}
    # ``tracks``: each track's coded frames hold both identities twice, so both tracks' most
    # frequent is one identity, held twice in every uncoded frame; distinct_in_frames then
    # gives each frame's subjects their tracklets' nearest coded identities: as ``nearest``
    by_tracks, summary = assign_identities(table, method="subjects", fill="tracks")
    assert summary["frames_made_distinct"] == 36  # the uncoded frames
    # (frame 15 is 5 frames from a coded frame of either identity: a tie either way)
    assert {14} <= set(frame[by_tracks != truth].tolist()) <= {14, 15}
    # swapped at frame 24 instead: track 1 is mostly a, track 2 mostly b, no frame holds one
    # identity twice, and ``tracks`` is wrong on the whole stretch after the swap
    table, truth = _swapped_pair(24, rng)
    by_tracks, summary = assign_identities(table, method="subjects", fill="tracks")
    if (by_tracks[table["frame"] == 0] != truth[table["frame"] == 0]).any():
        truth = 1 - truth
    assert summary["frames_made_distinct"] == 0
    uncoded = ~table["texture_valid"]
    for s in (1, 2):
        assert len(set(by_tracks[uncoded & (table["subject_id"] == s)].tolist())) == 1
    assert (by_tracks != truth).sum() == 2 * 2 * 15  # 2 tracks x 2 cameras x 25..39 but 30
    with pytest.raises(ValueError, match="fill"):
        assign_identities(table, fill="app")


def test_tracklets_cut_where_the_tracker_forced_a_link_carry_no_identity_across():
    """The swap above made by forced links (nsd.inference.tracking's bound on live tracks):
    the export cuts each track there into tracklets (``tracklet_id``), and the uncoded rows
    of frames 14 and 15 take the identity of their own tracklet's nearest coded frame, 20,
    not the track's, 10: no row is wrong. Without the column, as before."""
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(4)
    table, truth = _swapped_pair(14, rng)
    frame = table["frame"]
    table["tracklet_id"] = table["subject_id"] * 10 + (frame >= 14)
    near, summary = assign_identities(table, method="subjects", fill="nearest")
    assert summary["identities"] == 2 and summary["tracks"] == 4
    if (near[frame == 0] != truth[frame == 0]).any():
        truth = 1 - truth
    assert (near == truth).all()
    del table["tracklet_id"]
    by_tracks = assign_identities(table, method="subjects")[0]
    if (by_tracks[frame == 0] != truth[frame == 0]).any():
        by_tracks = 1 - by_tracks
    assert set(frame[by_tracks != truth].tolist()) == {14, 15}


@pytest.mark.parametrize("fill", ["nearest", "tracks"])
def test_a_tracklet_without_a_code_takes_its_tracks_identity(fill):
    """Track 1 is cut into three tracklets, the middle one (frames 22-27) holding no coded
    frame: its rows take track 1's identity (nearest: at frames 20 and 30; tracks: the
    track's most frequent), not -1."""
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(5)
    a, b = np.eye(8)[0], np.eye(8)[1]
    table = _track_table([(1, range(40), a), (2, range(40), b)], rng)
    table["texture_valid"] = table["frame"] % 10 == 0
    frame, track = table["frame"], table["subject_id"]
    table["tracklet_id"] = track * 10 + (frame >= 22) + (frame >= 28)
    identity, summary = assign_identities(table, method="subjects", fill=fill)
    assert summary["tracks"] == 4  # the tracklets with a code: 1's first and last, 2's three
    assert (identity >= 0).all()
    assert len(set(identity[track == 1].tolist())) == 1
    assert identity[track == 1][0] != identity[track == 2][0]


def test_distinct_in_frames_known_case():
    """Frame 5: subjects 1 and 2 both hold identity 0 after the fill, subject 3 identity 2.
    Subject 1's tracklet has identity 0 coded at frame 4, subject 2's tracklet has 0 at
    frame 0 and 1 at frame 8: 1 keeps 0 (1 frame away), 2 takes 1 (3 frames), 3 keeps 2.
    Frame 6 has no duplicate and is left alone, whatever its support."""
    from netepu.reid.identities import distinct_in_frames

    #                  frame  subject piece coded identity
    rows = np.array([[4, 1, 10, 1, 0], [0, 2, 20, 1, 0], [8, 2, 20, 1, 1], [2, 3, 30, 1, 2],
                     [5, 1, 10, 0, 0], [5, 1, 10, 0, 0], [5, 2, 20, 0, 0], [5, 3, 30, 0, 2],
                     [6, 1, 10, 0, 1], [6, 2, 20, 0, 0]])
    frame, subject, piece, coded, identity = (rows[:, c].copy() for c in range(5))
    assert distinct_in_frames(identity, frame, subject, piece, coded.astype(bool), 3) == 1
    assert identity.tolist() == [0, 0, 1, 2, 0, 0, 1, 2, 1, 0]
    again = identity.copy()
    assert distinct_in_frames(again, frame, subject, piece, coded.astype(bool), 3) == 0
    assert (again == identity).all()
    # a subject whose tracklet has no coded frame of an identity falls back on its track
    rows = np.array([[0, 1, 10, 1, 0], [0, 2, 20, 1, 1], [3, 1, 11, 0, 1], [3, 2, 20, 0, 1]])
    frame, subject, piece, coded, identity = (rows[:, c].copy() for c in range(5))
    assert distinct_in_frames(identity, frame, subject, piece, coded.astype(bool), 2) == 1
    assert identity[2:].tolist() == [0, 1]  # subject 1 by its track's frame 0
    assert distinct_in_frames(identity, frame, subject, piece, coded.astype(bool), 1) == 0


def test_one_coded_frame_with_wrong_codes_does_not_flip_the_rows_around_it():
    """The codes of coded frame 20 are swapped between the two subjects (a bad inversion),
    the tracks are right: the coded rows of frame 20 follow their codes, but the uncoded
    rows around it keep their track's identity (smoothed over neighbouring coded frames)."""
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(6)
    a, b = np.eye(8)[0], np.eye(8)[1]
    table = _track_table([(1, range(40), a), (2, range(40), b)], rng, cameras=("a", "b"))
    truth = (table["subject_id"] == 2).astype(int)
    frame = table["frame"]
    table["texture"][frame == 20] = table["texture"][frame == 20][:, [1, 0, 2, 3, 4, 5, 6, 7]]
    table["texture_valid"] = frame % 10 == 0
    # the fill under the codes' identities is what is tested (method=auto judges the codes
    # by pairs of coded frames 25 apart, of which four coded frames give one per track)
    identity, _ = assign_identities(table, method="subjects", fill="nearest")
    if (identity[frame == 0] != truth[frame == 0]).any():
        truth = 1 - truth
    assert set(frame[identity != truth].tolist()) == {20}


def test_subject_identities_pool_the_cameras_of_a_subject_frame():
    """In camera "c" each subject is half hidden by the other and its code leans to the other
    individual's (0.4 own + 0.6 other): ``rows`` decides that camera's rows alone and swaps
    them; ``subjects`` pools the three cameras of each subject-frame and gets every row."""
    from netepu.reid.identities import assign_identities

    rng = np.random.default_rng(5)
    a, b = np.eye(8)[0], np.eye(8)[1]
    table = _track_table([(1, range(12), a), (2, range(12), b)], rng, cameras=("a", "b", "c"))
    truth = (table["subject_id"] == 2).astype(int)
    in_c = table["camera"] == "c"
    own, other = np.where(truth[in_c, None] == 0, a, b), np.where(truth[in_c, None] == 0, b, a)
    table["texture"][in_c] = 0.4 * own + 0.6 * other + 0.05 * rng.normal(size=own.shape)

    def right(identity):
        return max((identity == truth).mean(), (identity == 1 - truth).mean())

    by_rows, _ = assign_identities(table, method="rows")
    by_subjects, summary = assign_identities(table, method="subjects")
    assert summary["identities"] == 2
    assert right(by_subjects) == 1.0
    assert right(by_rows) == pytest.approx(2 / 3)  # camera c swapped


def test_rows_without_a_code_take_the_identity_of_their_appearance():
    """Codes on every 3rd frame decide who is whom; the tracks swap individuals at frame 5,
    and the rows between coded frames follow their own appearance vector, not their track;
    two rows of one camera-frame never share an identity."""
    from netepu.reid.identities import transfer_identities

    rng = np.random.default_rng(3)
    frames = np.repeat(np.arange(9), 2)
    who = np.tile([0, 1], 9)  # the true individual of each row (one camera)
    subject = np.where(frames < 5, who + 1, 2 - who)  # the tracks swap at frame 5
    app = np.eye(4)[who] + 0.1 * rng.normal(size=(18, 4))
    coded = frames % 3 == 0
    identity = np.where(coded, 1 - who, -1)  # the codes named individual 0 "1"
    table = {"camera": np.array(["a"] * 18), "frame": frames, "subject_id": subject, "app": app}
    out = transfer_identities(table, identity, coded)
    assert np.array_equal(out, 1 - who)  # every row right, the swapped tracks included
    assert np.array_equal(out[coded], identity[coded])  # the coded rows keep theirs
    app[2:4] = np.eye(4)[0]  # both rows of frame 1 look like individual 0: still distinct
    out = transfer_identities(table, identity, coded)
    assert sorted(out[2:4].tolist()) == [0, 1]


def test_constrained_kmeans_against_exhaustive_search():
    """On small problems with separated clusters, the constrained k-means reaches the
    assignment of least total cosine distance among all that keep each group's rows apart."""
    import itertools

    from netepu.reid.identities import constrained_kmeans

    rng = np.random.default_rng(3)
    centres = np.eye(6)[:3]
    for trial in range(5):
        groups = np.repeat(np.arange(4), 3)
        truth = np.concatenate([rng.permutation(3) for _ in range(4)])
        codes = centres[truth] + 0.2 * rng.normal(size=(12, 6))
        start = centres + 0.3 * rng.normal(size=(3, 6))
        labels, found = constrained_kmeans(codes, groups, start)
        u = codes / np.linalg.norm(codes, axis=1, keepdims=True)

        def cost(lab, u=u):  # total cosine distance of the rows to their cluster's mean direction
            total = 0.0
            for j in np.unique(lab):
                m = u[lab == j].mean(0)
                total += (1 - u[lab == j] @ (m / np.linalg.norm(m))).sum()
            return total

        perms = list(itertools.permutations(range(3)))
        best = min(cost(np.concatenate(p)) for p in itertools.product(perms, repeat=4))
        assert cost(labels) == pytest.approx(best, abs=1e-9), trial
        assert found == pytest.approx(best, abs=1e-9)  # the cost it reports
        for g in range(4):
            assert sorted(labels[groups == g].tolist()) == [0, 1, 2]


def test_identity_accuracy_of_ground_truth_rows(tmp_path):
    """An 'export' made of the ground-truth masks: the true identities score 1, a mapping
    that swaps identities in later frames is wrong there in time but not across views;
    only the rows given an identity are scored."""
    from nsd.evaluation.identity import identity_accuracy

    scene = write_scene(tiny_config(num_frames=20), tmp_path / "scene")
    gt = json.loads((scene / "gt" / "coco.json").read_text())
    images = {im["id"]: im for im in gt["images"]}
    export = tmp_path / "export"
    export.mkdir()
    anns = [{**a, "subject_id": a["identity_id"]} for a in gt["annotations"]]
    (export / "subjects.coco.json").write_text(json.dumps({**gt, "annotations": anns}))
    ids = [a["id"] for a in anns]
    right = {a["id"]: a["identity_id"] for a in anns}
    acc = identity_accuracy(export, scene, ids, [right[i] for i in ids])
    assert acc["matched_rows"] == len(anns)
    assert acc["identity_accuracy"] == acc["cross_view_accuracy"] == acc["cross_time_accuracy"] == 1
    late = {a["id"] for a in anns if images[a["image_id"]]["frame"] >= 10}
    acc = identity_accuracy(
        export, scene, ids, [1 - right[i] if i in late else right[i] for i in ids]
    )
    assert acc["cross_view_accuracy"] == 1  # within a frame, identities still agree
    assert acc["cross_time_accuracy"] < 0.8
    share = max(len(late), len(anns) - len(late)) / len(anns)
    assert acc["identity_accuracy"] == pytest.approx(share)
    # split by a scripted contact from frame 10 on: one best mapping for all rows, so one
    # part is all right and the other all wrong, and the whole is their weighted mean
    touching = {t: t >= 10 for t in range(20)}
    acc = identity_accuracy(
        export, scene, ids, [1 - right[i] if i in late else right[i] for i in ids],
        touching=touching)
    apart, touch = acc["identity_accuracy_apart"], acc["identity_accuracy_touching"]
    assert sorted([apart, touch]) == [0.0, 1.0]
    whole = (apart * (len(anns) - len(late)) + touch * len(late)) / len(anns)
    assert acc["identity_accuracy"] == pytest.approx(whole)
    early = [i for i in ids if i not in late]
    acc = identity_accuracy(export, scene, early, [right[i] for i in early])
    assert acc["matched_rows"] == len(early) and acc["identity_accuracy"] == 1


def test_presence_is_one_until_its_start_step(tiny_scene):
    """prior_presence.from_step: the detector's presence is 1 before it, learned after it."""
    from nsd.io.scene_data import SceneData
    from nsd.training.task import NSDTask
    from tests.nsd.training.test_train import tiny_cfg

    cfg = tiny_cfg(
        "model.detector.presence=true",
        "model.detector.presence_init=0.3",
        "prior_presence=sparse",
        "prior_presence.from_step=2",
    )
    task = NSDTask(cfg, SceneData(tiny_scene, (32, 24), val_fraction=0.25))
    rng = np.random.default_rng(0)
    images, bgs = task.data.views(0)
    for step, expected in ((0, 1.0), (1, 1.0), (2, 0.3), (3, None)):
        losses = task.training_step(step, rng)
        p = task.model.detector(images, bgs).presence
        if expected is not None:
            assert torch.allclose(p, torch.full_like(p, expected), atol=1e-4), step
        if step < 2:
            assert float(losses["prior_presence"]) == 1.0  # constant: no pressure yet


def test_constrained_linkage_never_joins_co_visible_tracks():
    from netepu.reid.identities import constrained_average_linkage

    dist = np.array([[0, 0.1, 0.9], [0.1, 0, 0.8], [0.9, 0.8, 0]])
    apart = np.zeros((3, 3), bool)
    assert constrained_average_linkage(dist, apart, 2).tolist() == [0, 0, 1]
    apart[0, 1] = apart[1, 0] = True
    assert constrained_average_linkage(dist, apart, 2).tolist() == [0, 1, 1]
    apart[:] = ~np.eye(3, dtype=bool)  # all seen together: three identities whatever k
    assert constrained_average_linkage(dist, apart, 1).tolist() == [0, 1, 2]


def test_default_run_takes_the_builtin_model_of_the_scenes_species(tmp_path, tiny_run):
    """A scene that declares its species gets keypoints, texture codes and code identities
    from the shipped model with nsd-run's defaults; footage that does not is told why."""
    from netepu.pipeline.species_models import MODELS, builtin_models

    scene = write_scene(tiny_config(), tmp_path / "scene")
    out = tmp_path / "run"
    res = run_pipeline(_cfg(scene, out, "train.data.image_size=[48,48]", "evaluate.max_frames=2",
                            "netepu.keypoints.frame_step=3", "netepu.keypoints.steps=4",
                            "netepu.keypoints.templates=1", "netepu.keypoints.min_area=1"))
    shipped = f"builtin:{builtin_models()['biped']['sha256']}"
    record = json.loads((out / "pipeline.json").read_text())
    assert record["keypoints"]["status"] == record["texture"]["status"] == "ran"
    marker = json.loads((out / "keypoints" / "stage.json").read_text())
    assert marker["config"]["geometry"] == shipped
    assert res["texture"].summary["encoded"] > 0
    assert res["identities"].summary["column"] == "texture_reid"
    assert str(MODELS) not in json.dumps(res["keypoints"].summary)  # keyed by hash, not path
    _, _, results = tiny_run  # the checked-in tiny scene declares no species
    assert "does not declare its species" in results["keypoints"].summary["disabled"]


def test_a_scene_of_two_species_fits_both_bodies_and_assigns_identities_within_each(tmp_path):
    """A scene that declares bipeds and quadrupeds: every subject-frame is inverted with both
    built-in geometry models, takes one species (species.csv), is coded by that species'
    texture model only, and identities are numbered species by species."""
    from netepu.pipeline.species_choice import read_species_csv
    from nsd.io.embeddings import read_embeddings
    from nsd.synth.skeleton import get_species

    scene = write_scene(tiny_config(species=["biped", "quadruped"], num_individuals=2),
                        tmp_path / "scene")
    out = tmp_path / "run"
    res = run_pipeline(_cfg(scene, out, "train.data.image_size=[48,48]", "evaluate.max_frames=2",
                            "netepu.keypoints.frame_step=3", "netepu.keypoints.steps=4",
                            "netepu.keypoints.templates=1", "netepu.keypoints.min_area=1"))
    kp = out / "keypoints"
    choices = read_species_csv(kp / "species.csv")
    fitted = {s: np.load(kp / s / "all" / "keypoints3d.npz") for s in ("biped", "quadruped")}
    assert len(choices) == len(fitted["biped"]["subject_frame"]) > 0
    for s, z in fitted.items():  # each body's own keypoints
        assert z["subject_keypoints"].shape[1:] == (get_species(s).num_keypoints, 3)
    for c in choices:  # the lower loss, unless the track's neighbours outvote it
        assert c.losses.keys() == {"biped", "quadruped"}
    kept = res["keypoints"].summary["species"]
    assert sum(kept.values()) == len(choices)
    for s in ("biped", "quadruped"):
        with np.load(kp / s / "keypoints3d.npz") as z:
            mine = {(c.frame, c.subject_id) for c in choices if c.species == s}
            assert set(zip(z["subject_frame"].tolist(), z["subject_id"].tolist(),
                           strict=True)) == mine
            table = read_embeddings(out / "texture" / s)
            assert np.array_equal(table["texture_valid"], np.isin(table["id"], z["id"]))
    summary = res["identities"].summary
    assert set(summary["species"]) == {"biped", "quadruped"}
    rows = sum(summary["species"][s]["rows"] for s in ("biped", "quadruped"))
    _, *lines = (out / "identities" / "identities.csv").read_text().split()
    identified = sum(int(line.split(",")[4]) >= 0 for line in lines)
    assert identified <= rows <= len(lines) and summary["identities"] >= 1
    acc = res["keypoints"].summary["species_accuracy"]
    assert acc["scored"] == 0 or 0 <= acc["accuracy"] <= 1
    formats = json.loads((out / "formats" / "stage.json").read_text())["config"]
    assert formats["keypoints"] == ["biped", "quadruped"]  # each species on its skeleton
    labels = sio.load_slp(str(out / "formats" / "subjects.slp"))
    on = {sk.name: sk.node_names for sk in labels.skeletons}
    assert on == {s: list(get_species(s).keypoint_names) for s in ("biped", "quadruped")}
    fitted = {s: set(np.load(kp / s / "keypoints3d.npz")["id"].tolist()) for s in on}
    assert sum(res["formats"].summary["skeletons"].values()) > 0
    for s, n in res["formats"].summary["skeletons"].items():  # instances of fitted rows
        assert n <= len(fitted[s])


def test_every_run_writes_a_label_free_quality_report(tiny_run):
    _, out, results = tiny_run
    q = results["quality"].summary
    report = json.loads((out / "quality" / "quality.json").read_text())
    assert report["summary"] == q["summary"] and report["warnings"] == q["warnings"]
    assert 0 <= q["summary"]["explained"] <= 1 and 0 <= q["summary"]["spill"] <= 1
    assert q["summary"]["consistency"] is None  # two cameras: no hull of the others
    frames = [f["frame"] for f in report["frames"]]
    worst = sorted(report["frames"], key=lambda f: -f["badness"])[: len(q["worst"])]
    assert q["worst"] == [f["frame"] for f in worst] and set(q["worst"]) <= set(frames)
    assert sorted(q["files"]) == sorted(f"frame_{t:06d}.png" for t in q["worst"])
    assert all(cv2.imread(str(out / "quality" / "worst" / f)) is not None for f in q["files"])
    assert "| explained |" in (out / "quality" / "quality.md").read_text()


def test_identity_settings_are_validated_against_the_methods_the_code_has():
    """nsd's config rules cannot import netepu (the layout), so they spell the identity
    methods again: they must be exactly the code's (plus ``app``, the stage's own fill)."""
    from netepu.reid.identities import FILL_METHODS, IDENTITY_METHODS
    from nsd.core.validation import RULES

    assert set(RULES["run"]["netepu.identities.method"].choices) == set(IDENTITY_METHODS)
    assert set(RULES["run"]["netepu.identities.fill"].choices) == {*FILL_METHODS, "app"}


@pytest.mark.parametrize(("prog", "app", "key"), [
    ("nsd-run", "run", "netepu.keypoints.workers"), ("nsd-export", "export", "workers")])
def test_worker_counts_take_a_number_or_auto_on_the_command_line(prog, app, key):
    """``auto`` defaults must not make a number a type error (nsd-run refused
    ``netepu.keypoints.workers=1`` as "must be a string")."""
    from nsd.core.app import check_command_line

    for good in ("1", "3", "auto"):
        check_command_line(prog, app, [f"{key}={good}"])  # no SystemExit
    for bad in ("0", "many"):
        with pytest.raises(SystemExit):
            check_command_line(prog, app, [f"{key}={bad}"])


def test_motion_jump_takes_metres_or_auto_on_the_command_line(capsys):
    from nsd.core.app import check_command_line

    for good in ("0.3", "2", "auto"):
        check_command_line("nsd-run", "run", [f"netepu.identities.jump={good}"])
    for bad in ("0", "-1", "far"):
        with pytest.raises(SystemExit):
            check_command_line("nsd-run", "run", [f"netepu.identities.jump={bad}"])
        assert "netepu.identities.jump" in capsys.readouterr().err


def test_motion_without_positions_is_a_clear_error_and_auto_falls_back(random_cameras, tmp_path):
    """An export whose subjects are each seen by one camera has no world position:
    ``method=motion`` is refused naming the export and what to use; ``auto`` gets nothing to
    move by (and then takes the tracks: the test above)."""
    import json

    from omegaconf import OmegaConf
    from pycocotools import mask as mask_utils

    from netepu.pipeline.stages import _motion
    from nsd.cameras.calibration import CameraRig
    from nsd.core.errors import ConfigError

    rig = CameraRig(random_cameras)
    m = np.zeros((rig[0].size[1], rig[0].size[0]), np.uint8, order="F")
    m[10:15, 10:15] = 1
    rle = mask_utils.encode(m)
    rle["counts"] = rle["counts"].decode()
    anns = [{"id": n + 1, "image_id": n + 1, "camera": rig[n].name, "frame": n,
             "subject_id": 1, "segmentation": rle, "bbox": [10, 10, 5, 5]} for n in range(3)]
    images = [{"id": a["image_id"], "camera": a["camera"], "frame": a["frame"]} for a in anns]
    (tmp_path / "subjects.coco.json").write_text(json.dumps({"images": images,
                                                             "annotations": anns}))
    i = OmegaConf.create({"method": "motion", "jump": "auto"})
    with pytest.raises(ConfigError, match=r"method=motion needs subjects seen by two"):
        _motion(tmp_path, rig, "texture_reid", i, 48)
    i.method = "auto"  # asked only if the codes fail; nothing to move by, so the tracks
    positions, jump = _motion(tmp_path, rig, "texture_reid", i, 48)
    assert positions() == {} and jump > 0
    i.method = "subjects"  # the codes asked for: nothing to decode
    assert _motion(tmp_path, rig, "texture_reid", i, 48) is None
