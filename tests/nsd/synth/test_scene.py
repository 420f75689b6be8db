"""Scene folders: footage layout, COCO ground truth, dense maps, determinism, atomicity, config."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

import nsd.synth.scene as scene_mod
from nsd.cameras.calibration_io import read_calibration
from nsd.core.errors import ConfigError
from nsd.io.footage import MultiViewFootage
from nsd.synth import (
    SceneConfig,
    SyntheticScene,
    build_world,
    default_scene,
    tiny_config,
    write_scene,
)
from nsd.synth.scene import default_config

ROOT = Path(__file__).resolve().parents[3]
# pycocotools 2.0 + numpy 2: a harmless deprecation warning per decoded mask
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A tiny scene with 3 individuals (two species) forced close together."""
    cfg = tiny_config(num_individuals=3, species=["biped", "quadruped"], num_frames=5)
    return write_scene(cfg, tmp_path_factory.mktemp("synth") / "tiny")


def _rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def _coco(scene: Path) -> COCO:
    coco = COCO()
    coco.dataset = json.loads((scene / "gt" / "coco.json").read_text())
    coco.createIndex()
    return coco


class TestLayout:
    def test_readable_by_multiview_footage(self, tiny):
        f = MultiViewFootage(tiny)
        assert f.num_views == 2 and f.num_frames == 5 and f.camera_names == ["cam0", "cam1"]
        frame = f.frame(3)
        assert frame.shape == (2, 48, 48, 3)
        np.testing.assert_array_equal(frame[1], _rgb(tiny / "cam1" / "000003.png"))
        meta = SyntheticScene(tiny).meta
        assert read_calibration(tiny).names == [c["name"] for c in meta["cameras"]]

    def test_metadata(self, tiny):
        meta = SyntheticScene(tiny).meta
        assert meta["num_frames"] == 5 and meta["image_size"] == [48, 48]
        assert [i["species"] for i in meta["individuals"]] == ["biped", "quadruped", "biped"]
        assert [i["identity_id"] for i in meta["individuals"]] == [0, 1, 2]
        assert len({i["texture_id"] for i in meta["individuals"]}) == 3  # distinct textures
        assert set(meta["species"]) == {"biped", "quadruped"}
        assert len(meta["species"]["quadruped"]["keypoint_names"]) == 25
        assert (
            meta["config"]
            == tiny_config(
                num_individuals=3, species=["biped", "quadruped"], num_frames=5
            ).to_dict()
        )
        for key in ("amodal_overlap_fraction", "visible_box_overlap_fraction"):
            assert 0.0 <= meta["statistics"][key] <= 1.0
        for name in meta["files"]:
            found = list(tiny.glob(name.replace("<cam>", "*").replace("<frame:06d>", "*")))
            assert found, f"scene.json documents {name} but it is missing"

    def test_preview_written(self, tiny):
        img = cv2.imread(str(tiny / "gt" / "preview.png"))
        assert img is not None and img.shape[0] >= 2 * 48 and img.shape[1] >= 4 * 48


class TestCoco:
    def test_loadable_and_complete(self, tiny):
        coco = _coco(tiny)
        assert len(coco.getImgIds()) == 2 * 5
        img = coco.loadImgs(1)[0]
        assert {"id", "file_name", "width", "height", "camera", "frame"} <= set(img)
        assert (tiny / img["file_name"]).is_file()
        cats = {c["name"]: c for c in coco.loadCats(coco.getCatIds())}
        assert len(cats["biped"]["keypoints"]) == 17 and len(cats["quadruped"]["keypoints"]) == 25
        ann = coco.loadAnns(coco.getAnnIds())[0]
        keys = {
            "segmentation",
            "bbox",
            "area",
            "iscrowd",
            "category_id",
            "amodal_segmentation",
            "amodal_bbox",
            "identity_id",
            "texture_id",
            "keypoints",
            "num_keypoints",
            "depth",
        }
        assert keys <= set(ann)
        assert isinstance(ann["segmentation"]["counts"], str)

    @pytest.mark.parametrize("iou_type", ["bbox", "segm"])
    def test_cocoeval_of_ground_truth_against_itself_is_perfect(self, tiny, iou_type):
        gt = _coco(tiny)
        dets = [
            {"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"],
             "segmentation": a["segmentation"], "score": 1.0}
            for a in gt.dataset["annotations"]
        ]  # fmt: skip
        E = COCOeval(gt, gt.loadRes(dets), iou_type)
        E.evaluate()
        E.accumulate()
        E.summarize()
        assert E.stats[0] == pytest.approx(1.0)

    def test_keypoint_cocoeval_per_species(self, tiny):
        gt = _coco(tiny)
        for cat in gt.loadCats(gt.getCatIds()):
            anns = gt.loadAnns(gt.getAnnIds(catIds=[cat["id"]]))
            dets = [{"image_id": a["image_id"], "category_id": a["category_id"],
                     "keypoints": a["keypoints"], "score": 1.0} for a in anns]  # fmt: skip
            E = COCOeval(gt, gt.loadRes(dets), "keypoints")
            E.params.catIds = [cat["id"]]
            E.params.kpt_oks_sigmas = np.array(cat["kpt_oks_sigmas"])
            E.evaluate()
            E.accumulate()
            E.summarize()
            assert E.stats[0] == pytest.approx(1.0)

    def test_masks_agree_with_dense_maps(self, tiny):
        """Visible inside amodal; union of visible masks = foreground = finite depth."""
        gt, scene = _coco(tiny), SyntheticScene(tiny)
        for img in gt.dataset["images"]:
            d = scene.dense(img["camera"], img["frame"])
            anns = gt.loadAnns(gt.getAnnIds(imgIds=[img["id"]]))
            union = np.zeros((48, 48), bool)
            for a in anns:
                vis = mask_utils.decode(a["segmentation"]).astype(bool)
                amo = mask_utils.decode(a["amodal_segmentation"]).astype(bool)
                assert not (vis & ~amo).any()
                np.testing.assert_array_equal(vis, d["instance"] == a["identity_id"])
                np.testing.assert_array_equal(amo, d["amodal"][a["identity_id"]])
                assert a["area"] == vis.sum()
                union |= vis
            np.testing.assert_array_equal(union, d["instance"] >= 0)
            np.testing.assert_array_equal(union, np.isfinite(d["depth"]))
            # outside the individuals the image is the static backdrop
            rgb = _rgb(tiny / img["file_name"])
            bg, _ = scene.background(img["camera"])
            np.testing.assert_array_equal(rgb[~union], bg[~union])
            assert d["nnopcs"].min() >= 0 and d["nnopcs"].max() <= 1
            assert (d["nnopcs"][~union] == 0).all()

    def test_projected_3d_keypoints_equal_stored_2d(self, tiny):
        rig = read_calibration(tiny)
        scene, gt = SyntheticScene(tiny), _coco(tiny)
        for identity, X in scene.keypoints3d.items():
            uv, vis = scene.keypoints2d[identity]
            for v, cam in enumerate(rig):
                for t in range(X.shape[0]):
                    proj, z = cam.project(X[t])
                    np.testing.assert_allclose(uv[t, v], proj, atol=1e-6)
                    W, H = cam.size
                    inside = (
                        (proj[:, 0] >= -0.5)
                        & (proj[:, 0] < W - 0.5)
                        & (proj[:, 1] >= -0.5)
                        & (proj[:, 1] < H - 0.5)
                    )
                    np.testing.assert_array_equal(vis[t, v] > 0, inside & (z > 0))
        for a in gt.dataset["annotations"]:
            img = gt.loadImgs(a["image_id"])[0]
            v = rig.index(img["camera"])
            kp = np.array(a["keypoints"]).reshape(-1, 3)
            uv, vis = scene.keypoints2d[a["identity_id"]]
            np.testing.assert_array_equal(kp[:, 2], vis[img["frame"], v])
            on = kp[:, 2] > 0
            np.testing.assert_allclose(kp[on, :2], uv[img["frame"], v][on], atol=1e-3)

    def test_depth_file_matches_3d_points(self, tiny):
        """A pixel's stored depth and NNOPCS come from a point on the individual's surface."""
        scene = SyntheticScene(tiny)
        rig = read_calibration(tiny)
        world = build_world(SceneConfig.from_dict(scene.meta["config"]))
        t = 2
        for v, cam in enumerate(rig):
            d = scene.dense(v, t)
            fg = np.argwhere(d["instance"] >= 0)[:20]
            for y, x in fg:
                X = cam.unproject(np.array([[x, y]], float), np.array([d["depth"][y, x]], float))[0]
                n = d["instance"][y, x]
                body = world.individuals[n].posed(world.poses(t)[n].to(torch.float64))
                rel = (torch.as_tensor(X) - body.centres).unsqueeze(-2)
                local = (rel @ body.axes).squeeze(-2)  # M^T (X - c) per ellipsoid
                r = (local / body.radii).norm(dim=-1).min()
                assert abs(float(r) - 1.0) < 1e-4  # on the surface of one of its ellipsoids


class TestDeterminismAndAtomicity:
    def test_same_seed_same_scene_other_seed_differs(self, tmp_path, tiny):
        cfg = tiny_config(num_individuals=3, species=["biped", "quadruped"], num_frames=5)
        again = write_scene(cfg, tmp_path / "again")
        for rel in ["calibration.toml", "cam0/000004.png", "cam1/000000.png", "gt/coco.json",
                    "gt/preview.png", "gt/background/cam0.png"]:  # fmt: skip
            assert (again / rel).read_bytes() == (tiny / rel).read_bytes(), rel
        a, b = SyntheticScene(again), SyntheticScene(tiny)
        for k, v in a.keypoints3d.items():
            np.testing.assert_array_equal(v, b.keypoints3d[k])
        for key in ("depth", "nnopcs", "amodal"):
            np.testing.assert_array_equal(a.dense("cam1", 3)[key], b.dense("cam1", 3)[key])
        other = write_scene(cfg.replace(seed=1), tmp_path / "other")
        assert (other / "cam0/000004.png").read_bytes() != (tiny / "cam0/000004.png").read_bytes()

    def test_interrupted_write_leaves_no_scene(self, tmp_path, monkeypatch):
        calls = []

        def failing_save(*args, **kwargs):
            calls.append(1)
            if len(calls) == 3:
                raise RuntimeError("disk full")

        monkeypatch.setattr(scene_mod, "save_dense", failing_save)
        with pytest.raises(RuntimeError, match="disk full"):
            write_scene(tiny_config(num_frames=2), tmp_path / "broken")
        assert list(tmp_path.iterdir()) == []

    def test_existing_scene_is_not_overwritten_by_default(self, tmp_path):
        (tmp_path / "s").mkdir()
        with pytest.raises(FileExistsError):
            write_scene(tiny_config(num_frames=1), tmp_path / "s")

    def test_video_footage(self, tmp_path):
        path = write_scene(tiny_config(num_frames=4, video=True, dense=False), tmp_path / "v")
        f = MultiViewFootage(path)
        assert f.num_frames == 4 and f.frame(2).shape == (2, 48, 48, 3)
        assert not list((path / "gt" / "dense" / "cam0").glob("0*.npz"))


class TestDefaultScene:
    def test_default_config_is_the_documented_default(self):
        cfg = default_config()
        assert cfg.num_individuals == 2 and cfg.num_frames == 300
        assert tuple(cfg.image_size) == (128, 128)
        assert len(build_world(cfg.replace(num_frames=1)).rig) == 4

    def test_switching_rig_kind_keeps_other_kinds_keys(self):
        cfg = default_config()
        nepumoo = cfg.replace(num_frames=1, rig={**cfg.rig, "kind": "nepumoo"})
        rig = build_world(nepumoo).rig
        assert len(rig) == 24 and rig.names[8] == "ring1_cam0"

    def test_cached_once(self, tmp_path):
        cfg = tiny_config(num_frames=2)
        p1 = default_scene(cache_root=tmp_path, config=cfg)
        assert p1.parent == tmp_path / "scenes" and (p1 / "gt" / "coco.json").is_file()
        stamp = (p1 / "gt" / "scene.json").stat().st_mtime_ns
        p2 = default_scene(cache_root=tmp_path, config=cfg)
        assert p2 == p1 and (p1 / "gt" / "scene.json").stat().st_mtime_ns == stamp
        p3 = default_scene(cache_root=tmp_path, config=cfg.replace(seed=5))
        assert p3 != p1

    def test_hydra_config_composes_to_the_default(self):
        from hydra import compose, initialize_config_module
        from omegaconf import OmegaConf

        with initialize_config_module("nsd.conf", version_base="1.3"):
            cfg = compose("synth", overrides=["num_individuals=3", "motion.interaction=free"])
        values = OmegaConf.to_container(cfg)
        sc = SceneConfig.from_dict(
            {k: v for k, v in values.items() if k not in ("out", "overwrite")}
        )
        assert sc.num_individuals == 3 and sc.motion.interaction == "free"
        default = default_config()
        assert sc.replace(num_individuals=2, motion=default.to_dict()["motion"]) == default


class TestConfigErrors:
    @pytest.mark.parametrize(
        "changes, key",
        [
            ({"num_individuals": 0}, "num_individuals"),
            ({"num_individuals": 9}, "num_individuals"),
            ({"species": ["horse"]}, "species"),
            ({"species": []}, "species"),
            ({"image_size": [0, 48]}, "image_size"),
            ({"image_size": [48]}, "image_size"),
            ({"num_frames": 0}, "num_frames"),
            ({"fps": 0}, "fps"),
            ({"texture_ids": [1]}, "texture_ids"),
            ({"texture_ids": [1, -2]}, "texture_ids"),
            ({"supersample": 2}, "supersample"),
            ({"rig": {"kind": "dome"}}, "rig.kind"),
            ({"rig": {"kind": "corners", "count": 5}}, "rig.count"),
            ({"rig": {"kind": "ring", "distortion": [0.1]}}, "rig.distortion"),
            ({"rig": {"kind": "ring", "lens": 1}}, "rig"),
            ({"motion": {"interaction": "fight"}}, "motion.interaction"),
            ({"motion": {"speed": 1}}, "motion"),
            ({"light": {"ambient": 2.0}}, "light.ambient"),
            ({"colour": "red"}, "colour"),
        ],
    )
    def test_bad_values_name_the_key(self, changes, key):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            build_world(tiny_config(**({"num_frames": 1} | changes)))

    def test_cli_writes_a_scene_and_reports_bad_values(self, tmp_path):
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        base = [
            sys.executable,
            "-m",
            "nsd.synth.cli",
            "num_frames=2",
            "image_size=[32,24]",
            "preview.zoom=1",
        ]
        ok = subprocess.run(
            [*base, f"out={tmp_path / 'cli'}"],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert ok.returncode == 0, ok.stderr
        assert MultiViewFootage(tmp_path / "cli").num_frames == 2
        assert not (tmp_path / "outputs").exists()  # Hydra leaves no run folder behind
        bad = subprocess.run(
            [*base, "num_individuals=0", f"out={tmp_path / 'bad'}"],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert bad.returncode == 2 and "num_individuals" in bad.stderr
        assert not (tmp_path / "bad").exists()
