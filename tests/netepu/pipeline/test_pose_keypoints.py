"""3D keypoints from NSD's pose regressor: rays, world poses, the pipeline's regressor source."""

from __future__ import annotations

import json

import numpy as np
import pytest

from netepu.pipeline.pose_keypoints import world_keypoints
from netepu.pipeline.run import run_pipeline
from nsd.core.errors import ConfigError
from nsd.cues.triangulation import nearest_point_to_rays
from tests.netepu.pipeline.test_run import _cfg


def test_nearest_point_to_rays_known_point_and_least_squares():
    from scipy.optimize import minimize

    rng = np.random.default_rng(0)
    point = np.array([0.3, -1.2, 0.8])
    origins = rng.normal(size=(4, 3)) * 5
    dirs = point - origins
    np.testing.assert_allclose(nearest_point_to_rays(origins, 3 * dirs), point, atol=1e-10)
    noisy = dirs + 0.2 * rng.normal(size=dirs.shape)  # rays that miss: least squares

    def cost(x):
        d = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
        r = (x - origins) - ((x - origins) * d).sum(1, keepdims=True) * d
        return (r**2).sum()

    ref = minimize(cost, np.zeros(3), method="BFGS", options={"gtol": 1e-10}).x
    np.testing.assert_allclose(nearest_point_to_rays(origins, noisy), ref, atol=1e-6)
    with pytest.raises(ValueError, match="parallel"):
        nearest_point_to_rays(origins[:2], np.array([[0, 0, 1.0], [0, 0, 2.0]]))
    with pytest.raises(ValueError, match="n >= 2"):
        nearest_point_to_rays(origins[:1], dirs[:1])


def test_world_keypoints_recover_a_world_pose_from_camera_frame_predictions():
    """Root-relative poses in each camera frame and rays through the body's centroid give
    back the world pose exactly; views that disagree are reported."""
    from nsd.synth import make_rig

    rng = np.random.default_rng(1)
    rig = make_rig("ring", (64, 64), count=4, radius=4.0, height=2.0)
    pose = rng.normal(size=(17, 3)) * 0.3 + np.array([0.2, -0.1, 0.9])
    rot = np.stack([c.R for c in rig])
    rel = np.stack([(pose - pose[0]) @ c.R.T for c in rig])  # camera frame, root-relative
    origins = np.stack([c.center for c in rig])
    centroid = pose.mean(0)
    kp, spread = world_keypoints(rel, rot, origins, centroid - origins)
    np.testing.assert_allclose(kp, pose, atol=1e-9)
    assert spread < 1e-12
    rel[1] += 0.05  # one view's prediction is off: the mean moves, the spread shows it
    kp, spread = world_keypoints(rel, rot, origins, centroid - origins)
    np.testing.assert_allclose(kp.mean(0), centroid, atol=1e-9)  # placed on the rays' point
    assert 0.01 < spread < 0.1


@pytest.fixture(scope="module")
def regressor_run(tmp_path_factory):
    from nsd.synth import tiny_config, write_scene

    root = tmp_path_factory.mktemp("pose_kp")
    scene = write_scene(tiny_config(), root / "scene")
    out = root / "run"
    # every training frame labelled: a barely trained decomposition's windows hold 3 or more
    # of an individual's projected keypoints in only a few camera-frames
    res = run_pipeline(
        _cfg(scene, out, "netepu.keypoints.source=regressor", "netepu.keypoints.frame_step=2",
             "netepu.keypoints.regressor_steps=3", "netepu.keypoints.label_fraction=1.0",
             "evaluate.max_frames=2")
    )  # fmt: skip
    return scene, out, res


def test_pipeline_regresses_keypoints_where_3d_labels_exist(regressor_run):
    """source=regressor: NSD's pose regressor trained on the scene's few labels gives every
    exported subject of the chosen frames world keypoints whose centroid lies on the point
    nearest to its box-centre rays; the texture stage is not needed for it."""
    from nsd.cameras.calibration_io import read_calibration

    scene, out, res = regressor_run
    kp_summary = res["keypoints"].summary
    assert "disabled" not in kp_summary and kp_summary["subject_frames"] > 0
    assert kp_summary["regressor"]["labelled_frames"] >= 1
    acc = kp_summary["accuracy"]  # scored on subjects matched to the truth (few: 4 steps)
    assert acc["inverted"] == kp_summary["subject_frames"] and acc["scored"] <= acc["inverted"]
    assert acc["scored"] == 0 or np.isfinite(acc["mpjpe_mm"])
    assert (out / "keypoints" / "pose" / "checkpoint.pt").is_file()
    rig = read_calibration(scene)
    coco = json.loads((out / "export" / "subjects.coco.json").read_text())
    images = {im["id"]: im for im in coco["images"]}
    anns = {a["id"]: a for a in coco["annotations"]}
    with np.load(out / "keypoints" / "keypoints3d.npz") as z:
        assert set(z["id"].tolist()) <= set(anns)
        assert z["keypoints"].shape == (len(z["id"]), 17, 3)
        assert set(z["subject_frame"].tolist()) <= {0, 2, 4}
        for t, sid, kp in zip(z["subject_frame"], z["subject_id"], z["subject_keypoints"],
                              strict=True):  # fmt: skip
            rows = [
                a for a in anns.values()
                if a["subject_id"] == sid and images[a["image_id"]]["frame"] == t
            ]  # fmt: skip
            cams = [rig[images[a["image_id"]]["camera"]] for a in rows]
            centres = [[a["bbox"][0] + a["bbox"][2] / 2 - 0.5, a["bbox"][1] + a["bbox"][3] / 2
                        - 0.5] for a in rows]  # fmt: skip
            dirs = np.stack([c.unproject(np.array([uv]))[0] for c, uv in zip(cams, centres,
                                                                            strict=True)])
            point = nearest_point_to_rays(np.stack([c.center for c in cams]), dirs)
            np.testing.assert_allclose(kp.mean(0), point, atol=1e-4)


def test_regressor_source_needs_3d_labels_and_fails_before_training(tiny_scene, tmp_path):
    with pytest.raises(ConfigError, match="no gt/"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run",  # a copy: the scene stage caches
                          "netepu.keypoints.source=regressor"))  # fmt: skip
    assert not (tmp_path / "run" / "train").exists()
    with pytest.raises(ConfigError, match=r"netepu\.keypoints\.source must be one of"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run2",
                          "netepu.keypoints.source=oracle"))  # fmt: skip
    with pytest.raises(ConfigError, match=r"netepu\.keypoints\.workers: a number >= 1 or auto"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run3", "netepu.keypoints.workers=0"))
    assert not (tmp_path / "run3" / "train").exists()
    missing = tmp_path / "no_such_initialiser.pt"
    with pytest.raises(ConfigError, match=r"netepu\.keypoints\.initialiser: .*no_such_init"):
        run_pipeline(_cfg(tiny_scene, tmp_path / "run4",
                          f"netepu.keypoints.initialiser={missing}"))  # fmt: skip
    assert not (tmp_path / "run4" / "train").exists()


def test_a_decomposition_checkpoint_is_not_a_pose_checkpoint(regressor_run):
    from netepu.pipeline.pose_keypoints import load_pose_checkpoint
    from nsd.core.errors import CheckpointError

    _, out, _ = regressor_run
    with pytest.raises(CheckpointError, match="stage=pose"):
        load_pose_checkpoint(out / "train" / "checkpoint.pt")
    model, pose, cfg = load_pose_checkpoint(out / "keypoints" / "pose" / "checkpoint.pt")
    assert cfg["stage"] == "pose" and pose.keypoints == 17 and not pose.training
    assert not model.training


def _slp_labels(scene, path, keep=lambda frame: True):
    """The scene's ground-truth 2D keypoints as a SLEAP file, individuals tracked."""
    import sleap_io as sio

    coco = json.loads((scene / "gt" / "coco.json").read_text())
    images = {im["id"]: im for im in coco["images"]}
    skeleton = sio.Skeleton([f"kp{k}" for k in range(17)])
    videos = {c: sio.Video(filename=sorted(str(p) for p in (scene / c).glob("*.png")))
              for c in ("cam0", "cam1")}
    tracks = {i: sio.Track(name=f"id{i}") for i in (0, 1)}
    frames: dict = {}
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        if not keep(im["frame"]):
            continue
        kp = np.asarray(a["keypoints"], np.float64).reshape(-1, 3)
        lf = frames.setdefault((im["camera"], im["frame"]), sio.LabeledFrame(
            video=videos[im["camera"]], frame_idx=im["frame"]))
        lf.instances.append(sio.Instance.from_numpy(
            np.where((kp[:, 2] > 0)[:, None], kp[:, :2], np.nan), skeleton=skeleton,
            track=tracks[a["identity_id"]]))
    sio.save_slp(sio.Labels(labeled_frames=list(frames.values()), videos=list(videos.values()),
                            skeletons=[skeleton], tracks=list(tracks.values())), str(path))
    return path


def test_pose_regressor_trains_from_a_users_2d_labels(regressor_run, tmp_path):
    """stage=pose with pose.labels=<SLEAP file>: the tracked 2D labels are triangulated
    into 3D labels; their training frames train the regressor, their held-out frames score
    it. Without a labelled held-out frame it stops before training, saying so."""
    from omegaconf import OmegaConf

    from nsd.core.trainer import load_checkpoint
    from nsd.training.train import train

    scene, out, _ = regressor_run
    ckpt = out / "train" / "checkpoint.pt"
    c = OmegaConf.create(load_checkpoint(ckpt)["config"])
    c.stage, c.init_from = "pose", str(ckpt)
    c.pose.labels = str(_slp_labels(scene, tmp_path / "all.slp"))
    c.trainer.max_steps, c.trainer.max_minutes, c.trainer.progress = 3, 0.0, False
    c.trainer.eval_at_minutes = []
    windows, c.model.num_windows = c.model.num_windows, "auto"  # the decomposition's
    metrics = train(c, tmp_path / "pose")
    assert metrics["labelled_frames"] >= 1 and np.isfinite(metrics["mpjpe_mm"])
    saved = load_checkpoint(tmp_path / "pose" / "checkpoint.pt")["config"]["model"]
    assert saved["num_windows"] == windows
    c.pose.labels = str(_slp_labels(scene, tmp_path / "train.slp", lambda f: f < 3))
    with pytest.raises(ConfigError, match="no labelled held-out frames"):
        train(c, tmp_path / "pose2")


def test_an_export_is_re_decomposed_with_the_inference_it_recorded(tiny_scene, tmp_path):
    """The regressor reads the windows the export made: an export that records no inference
    was single-image; one from before ``hull_contested`` had the hull's bonus everywhere."""
    from netepu.pipeline.pose_keypoints import _as_exported

    d = {"image_size": [32, 24]}
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"config": {}}))
    _, settings, _ = _as_exported(tmp_path, tiny_scene, d)
    assert settings.views == "single" and settings.colour_sigma == 0.0
    manifest.write_text(json.dumps({"config": {"inference": {"hull_ownership": 3.0}}}))
    _, settings, _ = _as_exported(tmp_path, tiny_scene, d)
    assert settings.views == "multiview" and settings.hull_contested == 3.0
    recorded = {"hull_ownership": 3.0, "hull_contested": 0.5}
    manifest.write_text(json.dumps({"config": {"inference": recorded}}))
    assert _as_exported(tmp_path, tiny_scene, d)[1].hull_contested == 0.5
