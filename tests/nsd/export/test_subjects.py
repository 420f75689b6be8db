"""nsd-export: the files equal the model's outputs, score like nsd-eval, and fail cleanly.

A tiny checkpoint is trained once per module (a few steps on a 2-camera x 6-frame
synthetic scene at its native 48 x 48, so exported pixels are the model's pixels).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from pycocotools.coco import COCO

from nsd.core.errors import CheckpointError, ConfigError, FootageError
from nsd.export.config import load_export_config
from nsd.export.subjects import export_subjects
from nsd.io.crops import read_crop_index, read_crops
from nsd.io.embeddings import read_embeddings
from nsd.io.mot import read_mot

ROOT = Path(__file__).resolve().parents[3]
NO_VIEWS = {"views.tensorboard": False, "views.tsne": False, "progress": False}


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    """(checkpoint.pt, scene) of a tiny decomposition trained for a few steps."""
    from nsd.synth import tiny_config, write_scene
    from nsd.training.train import train
    from tests.nsd.training.test_train import tiny_cfg

    root = tmp_path_factory.mktemp("export")
    scene = write_scene(tiny_config(), root / "scene")
    cfg = tiny_cfg(
        f"data.scene={scene}",
        "data.image_size=[48,48]",
        "trainer.max_steps=4",
        "trainer.progress=false",
        "trainer.checkpoint_every=0",
        "eval_frames=1",
    )
    train(cfg, root / "run")
    return root / "run" / "checkpoint.pt", scene


def _export(ckpt, scene, out, **changes):
    cfg = load_export_config(
        checkpoint=str(ckpt), scene=str(scene), out=str(out), **{**NO_VIEWS, **changes}
    )
    return export_subjects(cfg)


def _reference(ckpt, scene):
    """The model's own outputs on every frame, one frame (all views) at a time, with the
    export's default (multi-view) inference: the hull's clustering carried through the
    frames in order, the mixture decided for the scene, as the export does."""
    from nsd.inference.multiview import InferenceSettings, decompose_views, model_scene_track
    from nsd.io.scene_data import SceneData
    from nsd.model.checkpoint import load_decomposition

    trained = load_decomposition(ckpt)
    H, W = trained.frame_hw
    data = SceneData(scene, (W, H), val_fraction=0.0,
                     background=trained.config.data.background)  # as the export
    st = InferenceSettings.defaults()
    grid = st.grid(data.rig, data.frame_hw)
    V = data.num_views
    frames = range(len(data.frames))
    track = model_scene_track(trained.model, data.views, frames, grid, st.mixture)
    return data, [
        decompose_views(trained.model, *data.views(t), V, st, grid, track=track) for t in frames
    ]


def test_round_trip_equals_model_outputs(trained, tmp_path):
    ckpt, scene = trained
    s = _export(ckpt, scene, tmp_path / "out", batch_size=4)  # batches straddle frames
    data, decs = _reference(ckpt, scene)
    coco = COCO(str(s.out / "subjects.coco.json"))
    names = data.rig.names
    assert len(coco.imgs) == len(decs) * len(names) == s.camera_frames
    emb = read_embeddings(s.out)
    row = {int(i): k for k, i in enumerate(emb["id"])}
    n = 0
    for t, dec in enumerate(decs):
        for v, cam in enumerate(names):
            (img,) = [i for i in coco.imgs.values() if i["camera"] == cam and i["frame"] == t]
            anns = coco.loadAnns(coco.getAnnIds(imgIds=[img["id"]]))
            active = np.flatnonzero(dec.active[v].numpy())
            assert sorted(a["slot"] for a in anns) == active.tolist()
            for a in anns:
                k = a["slot"]
                np.testing.assert_array_equal(coco.annToMask(a), dec.masks[v, k].numpy() > 0.5)
                np.testing.assert_allclose(a["bbox"], dec.boxes[v, k].numpy())
                assert a["score"] == pytest.approx(float(dec.scores[v, k]), abs=1e-5)
                assert a["depth"] == pytest.approx(float(dec.depths[v, k]), abs=1e-5)
                r = row[a["id"]]
                assert (emb["camera"][r], emb["frame"][r], emb["slot"][r]) == (cam, t, k)
                assert emb["subject_id"][r] == a["subject_id"] >= 1
                assert emb["tracklet_id"][r] == a["tracklet_id"] >= 1
                np.testing.assert_allclose(emb["app"][r], dec.app[v, k].numpy(), atol=1e-5)
                n += 1
    assert n == s.subjects == len(emb["id"]) > 0
    # every window of a frame that the association matched across views shares a subject id
    for t in range(len(decs)):
        ids = [a for a in coco.dataset["annotations"] if a["frame"] == t]
        by_assoc = {}
        for a in ids:
            by_assoc.setdefault(a["association_id"], set()).add(a["subject_id"])
        assert all(len(v) == 1 for v in by_assoc.values())
    # a tracklet lies within one track
    track_of = {}
    for a in coco.dataset["annotations"]:
        assert track_of.setdefault(a["tracklet_id"], a["subject_id"]) == a["subject_id"]
    from nsd.io.embeddings import read_tracklets

    assert read_tracklets(s.out) == {(a["frame"], a["subject_id"]): a["tracklet_id"]
                                     for a in coco.dataset["annotations"]}
    assert read_tracklets(tmp_path) is None  # no table there
    # tracking.max_tracks=auto: never more tracks than windows (6 frames < max_gap: none closes)
    from nsd.model.checkpoint import load_decomposition

    windows = load_decomposition(ckpt).model.cfg.num_windows
    assert {a["subject_id"] for a in coco.dataset["annotations"]} <= set(range(1, windows + 1))


def test_crops_index_and_manifest_checksums(trained, tmp_path):
    ckpt, scene = trained
    s = _export(ckpt, scene, tmp_path / "out", **{"crop.size": 24, "crop.chunk": 5})
    coco = COCO(str(s.out / "subjects.coco.json"))
    index = read_crop_index(s.out / "crops")
    assert [r["id"] for r in index] == sorted(coco.anns) and len(index) == s.subjects
    assert len(list((s.out / "crops").glob("crops-*.npz"))) == -(-s.subjects // 5)
    first = index[0]
    ann = coco.anns[first["id"]]
    np.testing.assert_allclose(
        [first[k] for k in ("bbox_x", "bbox_y", "bbox_w", "bbox_h")], ann["bbox"], atol=0.01
    )
    crops, masks = read_crops(s.out / "crops", [first["id"]])
    assert crops.shape == (1, 24, 24, 3) and masks[0].any()  # the subject is in its crop
    manifest = json.loads((s.out / "manifest.json").read_text())
    assert manifest["counts"]["subjects"] == s.subjects
    assert manifest["checkpoint"]["step"] == 4 and manifest["scene"]["ground_truth"]
    for rel, meta in manifest["files"].items():
        assert hashlib.sha256((s.out / rel).read_bytes()).hexdigest() == meta["sha256"], rel
    assert set(manifest["files"]) >= {
        "subjects.coco.json",
        "embeddings.parquet",
        "tracks/cam0.txt",
        "crops/index.csv",
    }


def test_coco_ap_equals_nsd_eval(trained, tmp_path):
    from nsd.evaluation.checkpoint import evaluate_checkpoint
    from nsd.evaluation.decomposition import coco_ap
    from nsd.io.ground_truth import GroundTruth

    ckpt, scene = trained
    s = _export(ckpt, scene, tmp_path / "out")
    gt = GroundTruth.load(scene).coco
    dt = COCO(str(s.out / "subjects.coco.json"))
    assert set(dt.getImgIds()) <= set(gt.getImgIds())  # the scene's own image ids
    ours = coco_ap(gt, dt.dataset["annotations"], dt.getImgIds())
    theirs = evaluate_checkpoint(ckpt, scene, frames="all")
    for k in ("coco_bbox_ap", "coco_bbox_ap50", "coco_segm_ap", "coco_segm_ap50"):
        assert ours[k] == pytest.approx(theirs[k], abs=1e-9), k
    # nsd-eval writes these as JSON: numpy scalars (float32 mIoU sums) used to break it
    assert all(type(v) is float for v in theirs.values())
    json.loads(json.dumps(theirs))


def test_mot_files_parse_and_match_coco(trained, tmp_path):
    ckpt, scene = trained
    s = _export(ckpt, scene, tmp_path / "out", frames={"start": 1, "stop": None, "step": 2})
    coco = COCO(str(s.out / "subjects.coco.json"))
    assert sorted({i["frame"] for i in coco.imgs.values()}) == [1, 3, 5]
    for cam in ("cam0", "cam1"):
        rows = read_mot(s.out / "tracks" / f"{cam}.txt")
        anns = sorted(
            (a for a in coco.dataset["annotations"] if a["camera"] == cam),
            key=lambda a: (a["frame"], a["subject_id"]),
        )
        rows = rows[np.lexsort((rows[:, 1], rows[:, 0]))]
        assert len(rows) == len(anns) > 0
        np.testing.assert_array_equal(rows[:, 0], [a["frame"] + 1 for a in anns])
        np.testing.assert_array_equal(rows[:, 1], [a["subject_id"] for a in anns])
        np.testing.assert_allclose(rows[:, 2:6], [np.add(a["bbox"], [1, 1, 0, 0]) for a in anns])
        assert (np.diff(read_mot(s.out / "tracks" / f"{cam}.txt")[:, 0]) >= 0).all()


def test_projector_and_tsne(trained, tmp_path):
    ckpt, scene = trained
    s = _export(
        ckpt,
        scene,
        tmp_path / "out",
        **{"views.tensorboard": True, "views.tsne": True, "views.max_points": 10},
    )
    proj = list((s.out / "tensorboard").rglob("metadata.tsv"))
    assert len(proj) == 1 and (proj[0].parent / "sprite.png").is_file()
    lines = proj[0].read_text().splitlines()
    assert lines[0].split("\t") == ["subject_id", "camera", "frame"] and len(lines) == 11
    assert (s.out / "tsne.png").stat().st_size > 0
    assert s.manifest["views"] == {"tensorboard": True, "tsne": True}


def test_existing_folder_and_bad_settings(trained, tmp_path):
    ckpt, scene = trained
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="overwrite=true"):
        _export(ckpt, scene, out, overwrite=False)
    assert (out / "keep.txt").read_text() == "mine"
    with pytest.raises(ConfigError, match=r"frames \[99\] are outside"):
        _export(ckpt, scene, out, frames=[0, 99])
    with pytest.raises(ConfigError, match=r"crop\.size: must be >= 4"):
        _export(ckpt, scene, out, **{"crop.size": 0})
    with pytest.raises(ConfigError, match=r"no key 'crop\.sise'"):
        load_export_config(**{"crop.sise": 3})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing half-written


def test_missing_checkpoint(trained, tmp_path):
    _, scene = trained
    with pytest.raises(CheckpointError, match=r"checkpoint .*nope\.pt does not exist"):
        _export(tmp_path / "nope.pt", scene, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_camera_unknown_to_the_checkpoint(trained, tmp_path):
    ckpt, scene = trained
    other = tmp_path / "scene"
    shutil.copytree(scene, other)
    (other / "cam1").rename(other / "cam7")
    calib = other / "calibration.toml"
    calib.write_text(calib.read_text().replace('"cam1"', '"cam7"'))
    with pytest.raises(CheckpointError, match=r"cameras \['cam7'\].*not trained with") as e:
        _export(ckpt, other, tmp_path / "out")
    assert str(other) in str(e.value)
    assert not (tmp_path / "out").exists()
    s = _export(ckpt, other, tmp_path / "out", cameras=["cam0"])  # known cameras only
    assert sorted(p.name for p in (s.out / "tracks").iterdir()) == ["cam0.txt"]


def test_own_image_ids_without_ground_truth(trained, tmp_path):
    ckpt, scene = trained
    other = tmp_path / "scene"
    shutil.copytree(scene, other, ignore=shutil.ignore_patterns("gt"))
    s = _export(ckpt, other, tmp_path / "out", cameras=["cam1"], frames=[2, 5])
    images = COCO(str(s.out / "subjects.coco.json")).dataset["images"]
    assert [(i["id"], i["file_name"], i["camera"], i["frame"]) for i in images] == [
        (2 * 2 + 1 + 1, "cam1/000002.png", "cam1", 2),  # frame * C + c + 1, C = 2 cameras
        (5 * 2 + 1 + 1, "cam1/000005.png", "cam1", 5),
    ]
    assert (images[0]["width"], images[0]["height"]) == (48, 48)
    assert not s.manifest["scene"]["ground_truth"]
    # one camera: nothing to fuse, so single-image inference, and the manifest says so
    assert s.manifest["config"]["inference"]["views"] == "single"


def test_unreadable_frame_mid_export(trained, tmp_path):
    from nsd.io.footage import MultiViewFootage

    ckpt, scene = trained
    other = tmp_path / "scene"
    shutil.copytree(scene, other)
    MultiViewFootage(other, image_size=(48, 48)).background()  # cached: fails while streaming
    (other / "cam1" / "000003.png").write_bytes(b"not a png")
    with pytest.raises(FootageError, match=r"camera 'cam1' \(.*000003\.png, frame 3\)"):
        _export(ckpt, other, tmp_path / "out", batch_size=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no export, no partial


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in status


@pytest.mark.parametrize("workers", [1, 2])
def test_killed_export_leaves_no_export_folder(trained, tmp_path, workers):
    """Killed mid-export (SIGKILL): no export folder, and no worker process left behind."""
    ckpt, scene = trained
    out = tmp_path / "out"
    code = (
        "import multiprocessing, time, sys\n"
        "import nsd.export.subjects as e\n"
        "from nsd.export.config import load_export_config\n"
        "from nsd.export.writer import SubjectWriter\n"
        "orig = SubjectWriter.write\n"
        "def write(self, results):\n"
        "    orig(self, results)\n"
        "    pids = [p.pid for p in multiprocessing.active_children()]\n"
        "    print('written', *pids, flush=True); time.sleep(120)\n"
        "SubjectWriter.write = write\n"
        "cfg = load_export_config(checkpoint=sys.argv[1], scene=sys.argv[2], out=sys.argv[3],\n"
        "                         batch_size=1, progress=False, workers=int(sys.argv[4]))\n"
        "e.export_subjects(cfg)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(ckpt), str(scene), str(out), str(workers)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        said = proc.stdout.readline().split()
        assert said[:1] == ["written"]
        children = [int(p) for p in said[1:]]
        assert len(children) == (workers if workers > 1 else 0)
        partials = list(tmp_path.glob(".out.partial-*"))
        assert len(partials) == 1 and (partials[0] / "crops").is_dir()
    finally:
        proc.kill()
        proc.wait()
    assert not out.exists()
    for _ in range(100):  # the workers die with their parent
        if not any(_alive(pid) for pid in children):
            break
        time.sleep(0.05)
    assert not any(_alive(pid) for pid in children)
    s = _export(ckpt, scene, out)  # re-running starts afresh and removes the dead partial
    assert s.frames == 6 and not list(tmp_path.glob(".out.partial-*"))


def test_cli_runs_and_reports_bad_input(trained, tmp_path):
    ckpt, scene = trained
    cmd = [
        sys.executable,
        "-m",
        "nsd.cli.export",
        f"checkpoint={ckpt}",
        f"scene={scene}",
        f"out={tmp_path / 'out'}",
        "frames=[0,1]",
        "views.tsne=false",
        "progress=false",
    ]
    ok = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert "exported 2 frames (4 camera-frames" in ok.stdout
    assert json.loads((tmp_path / "out" / "manifest.json").read_text())["counts"]["frames"] == 2
    bad = subprocess.run(
        [*cmd[:3], f"checkpoint={tmp_path / 'missing.pt'}", *cmd[4:]],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert bad.returncode == 2 and "nsd-export: error: checkpoint" in bad.stderr


def test_threads_are_not_changed_by_the_library(trained, tmp_path):
    ckpt, scene = trained
    before = torch.get_num_threads()
    _export(ckpt, scene, tmp_path / "out", frames=[0], threads=1)
    assert torch.get_num_threads() == before


def test_nsd_eval_scores_labels_on_footage_without_ground_truth(trained, tmp_path):
    """Real footage has no gt/: nsd-eval labels= scores an export against a user's SLEAP
    labels alone; without export= it stops before any work, naming the key."""
    import sleap_io as sio

    ckpt, scene = trained
    s = _export(ckpt, scene, tmp_path / "out")
    real = tmp_path / "real"
    shutil.copytree(scene, real, ignore=shutil.ignore_patterns("gt", ".cache"))
    coco = json.loads((scene / "gt" / "coco.json").read_text())
    images = {im["id"]: im for im in coco["images"]}
    skeleton = sio.Skeleton([f"kp{k}" for k in range(17)])
    videos = {c: sio.Video(filename=sorted(str(p) for p in (real / c).glob("*.png")))
              for c in ("cam0", "cam1")}
    frames = {}
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        kp = np.asarray(a["keypoints"], np.float64).reshape(-1, 3)
        lf = frames.setdefault((im["camera"], im["frame"]), sio.LabeledFrame(
            video=videos[im["camera"]], frame_idx=im["frame"]))
        lf.instances.append(sio.Instance.from_numpy(
            np.where((kp[:, 2] == 2)[:, None], kp[:, :2], np.nan), skeleton=skeleton))
    slp = tmp_path / "labels.slp"
    sio.save_slp(sio.Labels(labeled_frames=list(frames.values()), videos=list(videos.values()),
                            skeletons=[skeleton]), str(slp))
    cmd = [sys.executable, "-m", "nsd.cli.evaluate", f"checkpoint={ckpt}", f"scene={real}",
           f"labels={slp}", f"out={tmp_path / 'ev'}"]
    bad = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert bad.returncode == 2 and "labels= scores an export: give export=" in bad.stderr
    ok = subprocess.run([*cmd, f"export={s.out}"], capture_output=True, text=True, cwd=ROOT,
                        timeout=300)
    assert ok.returncode == 0, ok.stderr
    metrics = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert "mask_miou" not in metrics  # no ground truth: the labels alone
    assert metrics["labels_labelled_instances"] == len(coco["annotations"])
    assert 0 <= metrics["labels_keypoints_in_mask"] <= 1
    assert np.isnan(metrics["labels_cross_view_identity"])  # untracked labels: no pairs
    assert "keypoints_in_mask" in (tmp_path / "ev" / "eval.md").read_text()


def test_frame_images_give_coco_real_image_paths(trained, tmp_path):
    """frame_images=true: every COCO image's file_name is a JPEG in the export that image
    tools open, the camera-frame itself (JPEG-close to the footage)."""
    import cv2

    from nsd.io.footage import MultiViewFootage

    ckpt, scene = trained
    s = _export(ckpt, scene, tmp_path / "out", frame_images=True, frames=[0, 3])
    coco = json.loads((s.out / "subjects.coco.json").read_text())
    assert len(coco["images"]) == 4  # 2 frames x 2 cameras
    footage = MultiViewFootage(scene)
    for im in coco["images"]:
        img = cv2.imread(str(s.out / im["file_name"]))
        assert img is not None and img.shape[:2] == (im["height"], im["width"])
        native = footage.sources[footage.camera_names.index(im["camera"])].read(im["frame"])
        assert np.abs(img[..., ::-1].astype(float) - native).mean() < 4.0
    manifest = json.loads((s.out / "manifest.json").read_text())
    assert any(k.startswith("images/") for k in manifest["files"])


def test_native_refine_auto_turns_on_for_footage_larger_than_training():
    """native_refine=auto: on when a camera's footage is larger than the training frames."""
    from types import SimpleNamespace

    from nsd.export.writer import SubjectWriter

    def writer(setting, native):
        w = SubjectWriter.__new__(SubjectWriter)
        w.cfg = {"native_refine": setting}
        w.inp = SimpleNamespace(trained=SimpleNamespace(frame_hw=(48, 64)), footage=SimpleNamespace(
            sources=[SimpleNamespace(size=native), SimpleNamespace(size=(64, 48))]))
        return w._native_refine()

    assert writer("auto", (640, 480)) and not writer("auto", (64, 48))
    assert writer(True, (64, 48)) and not writer(False, (640, 480))


def test_workers_write_the_same_files_as_one_process(trained, tmp_path):
    """Batches decomposed by 2 forked workers (1 thread each) give byte-identical files to one
    process with 1 thread: the results are taken back and written in frame order."""
    ckpt, scene = trained
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # the library runs workers=1 with the caller's threads
    try:
        one = _export(ckpt, scene, tmp_path / "one", batch_size=1, workers=1)
    finally:
        torch.set_num_threads(before)
    two = _export(ckpt, scene, tmp_path / "two", batch_size=1, workers=2, threads=2)
    assert (one.workers, two.workers) == (1, 2)
    assert two.manifest["timing"]["worker_peak_rss_mb"] > 0
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*")
                   if p.is_file() and p.name != "manifest.json")
    assert files == sorted(p.relative_to(tmp_path / "two") for p in (tmp_path / "two").rglob("*")
                           if p.is_file() and p.name != "manifest.json")
    for f in files:
        a, b = (tmp_path / "one" / f).read_bytes(), (tmp_path / "two" / f).read_bytes()
        if f.name == "subjects.coco.json":  # the date differs; every image and annotation not
            a, b = (json.loads(x) for x in (a, b))
            a["info"].pop("date_created"), b["info"].pop("date_created")
        assert a == b, f


def test_a_workers_error_reaches_the_caller_and_leaves_nothing(trained, tmp_path, monkeypatch):
    """An error raised in a worker (here: a frame that cannot be decoded, faked) stops the
    export with that error; no folder, no worker process left."""
    import multiprocessing

    from nsd.export.writer import SubjectWriter

    ckpt, scene = trained
    orig = SubjectWriter.decompose

    def decompose(self, items, clusters=None, mixture=True):
        if items[0][0] == 3:
            raise FootageError("camera 'cam1' (fake, frame 3): frame cannot be decoded")
        return orig(self, items, clusters)

    monkeypatch.setattr(SubjectWriter, "decompose", decompose)  # inherited by the fork
    with pytest.raises(FootageError, match="frame 3"):
        _export(ckpt, scene, tmp_path / "out", batch_size=1, workers=2, threads=2)
    assert list(tmp_path.iterdir()) == []
    assert multiprocessing.active_children() == []


def test_workers_setting():
    from nsd.core.processes import MAX_AUTO_WORKERS, resolve_workers

    assert resolve_workers("auto", 64, "cpu") == MAX_AUTO_WORKERS
    assert resolve_workers("auto", 2, "cpu") == 2
    assert resolve_workers("auto", 2, "cuda") == 1
    assert resolve_workers(1, 0, "cuda") == 1
    for bad in (0, -1, "many"):
        with pytest.raises(ConfigError, match="workers"):
            resolve_workers(bad, 0, "cpu")
    with pytest.raises(ConfigError, match="workers=2 needs a CPU"):
        resolve_workers(2, 0, "cuda")


def test_a_worker_killed_stops_the_export_with_a_message(trained, tmp_path, monkeypatch):
    """A worker killed mid-export (the kernel's out-of-memory killer) stops the export with a
    message that says what to lower, instead of waiting forever for its batch."""
    import os
    import signal

    from nsd.export.writer import SubjectWriter

    ckpt, scene = trained
    orig = SubjectWriter.decompose

    def decompose(self, items, clusters=None, mixture=True):
        if items[0][0] == 3:
            os.kill(os.getpid(), signal.SIGKILL)
        return orig(self, items, clusters)

    monkeypatch.setattr(SubjectWriter, "decompose", decompose)
    with pytest.raises(RuntimeError, match=r"worker process died.*lower workers= or batch_size="):
        _export(ckpt, scene, tmp_path / "out", batch_size=1, workers=2, threads=2)
    assert list(tmp_path.iterdir()) == []
