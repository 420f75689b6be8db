"""Keypoints of exported subjects: occluders from the other subjects, temporal smoothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pycocotools import mask as mask_utils

from netepu.pipeline.subject_keypoints import _others, smooth_tracks


def _row(image_id: int, subject: int, mask: np.ndarray) -> dict:
    rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"image_id": image_id, "subject_id": subject, "segmentation": rle}


def test_occluders_are_the_other_subjects_of_the_same_camera_frame():
    a, b, c = (np.zeros((6, 8), bool) for _ in range(3))
    a[1:3, 1:3], b[2:5, 2:6], c[0:2, 5:8] = True, True, True
    rows = {1: [_row(1, 10, a), _row(1, 11, b)], 2: [_row(2, 12, c)]}
    np.testing.assert_array_equal(_others(rows[1][0], rows), b)  # not itself, not image 2
    np.testing.assert_array_equal(_others(rows[1][1], rows), a)
    assert not _others(rows[2][0], rows).any()  # alone in its camera-frame


def test_smoothing_known_values_and_outliers():
    kp = np.zeros((2, 3))
    fits = [(0, 1, kp + 0.0, 0.5), (10, 1, kp + 1.0, 0.5), (20, 1, kp + 2.0, 0.5),
            (10, 2, kp + 7.0, 0.5)]
    same = smooth_tracks(fits, 0)
    for (_, _, k, _), s in zip(fits, same, strict=True):
        np.testing.assert_array_equal(s, k)
    out = smooth_tracks(fits, 10.0)
    w1, w2 = np.exp(-0.5), np.exp(-2.0)  # neighbours 10 and 20 frames away at sigma 10
    np.testing.assert_allclose(out[1], kp + 1.0)  # symmetric neighbours
    np.testing.assert_allclose(out[0], kp + (w1 * 1 + w2 * 2) / (1 + w1 + w2))
    np.testing.assert_allclose(out[3], kp + 7.0)  # another subject is never mixed in
    bad = [(0, 1, kp + 0.0, 0.1), (10, 1, kp + 5.0, 1.0), (20, 1, kp + 0.0, 0.1)]
    assert np.abs(smooth_tracks(bad, 10.0)[1]).max() < 0.3  # a poor fit (10x loss) weighs 1/100
    far = [(0, 1, kp + 0.0, 0.5), (100, 1, kp + 9.0, 0.5)]
    np.testing.assert_allclose(smooth_tracks(far, 10.0)[0], kp)  # beyond 3 sigma: no weight


def _hand_made_export(tmp_path, model, net):
    """Two bipeds (the shipped model's own renders of two poses 1.2 m apart) in 2 frames of
    4 cameras at 96 x 96: a scene folder with its calibration and an export folder."""
    import json

    import torch

    from netepu.geometry.maps import MapSettings, render_maps
    from netepu.pipeline.subject_keypoints import template_poses
    from nsd.cameras.calibration_io import write_toml
    from tests.netepu_world import ring

    rig = ring(4, size=(96, 96), radius=5.0, f=90.0)
    (tmp_path / "scene").mkdir()
    write_toml(rig, tmp_path / "scene" / "calibration.toml")
    cam = rig.stacked(torch.float32)
    poses = template_poses(net["data"], 4, seed=5)
    images, annotations = [], []
    for t in range(2):
        masks = []
        for s, dx in enumerate((-0.6, 0.6)):
            pose = poses[2 * t + s] - poses[2 * t + s].mean(0) + torch.tensor([dx, 0.0, 0.9])
            with torch.no_grad():
                maps = render_maps(model.query, model.prepare(model.encode(pose[None]), cam),
                                   (96, 96), MapSettings.from_config(net["render"]))
            masks.append(maps.silhouette.numpy())
        for v, c in enumerate(rig):
            images.append({"id": len(images), "frame": t, "camera": c.name, "height": 96,
                           "width": 96})
            for s in range(2):
                m = masks[s][v] & ~(masks[1 - s][v] if s else False)  # subject 0 in front
                if m.sum() < 16:
                    continue
                rle = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
                annotations.append({"id": len(annotations), "image_id": images[-1]["id"],
                                    "camera": c.name, "frame": t,
                                    "subject_id": s, "area": float(m.sum()),
                                    "segmentation": {"size": rle["size"],
                                                     "counts": rle["counts"].decode()}})
    (tmp_path / "export").mkdir()
    (tmp_path / "export" / "subjects.coco.json").write_text(
        json.dumps({"images": images, "annotations": annotations}))
    return tmp_path / "scene", tmp_path / "export"


def test_the_keypoints_do_not_depend_on_the_workers(tmp_path):
    """Two processes (subject-frames side by side; with warm starts each subject's chain in
    one; the heading's refits side by side too) give the keypoints one process gives, in the
    same rows, at one torch thread per process (more threads round sums otherwise)."""
    from netepu.geometry.model import load_geometry_model
    from netepu.pipeline.species_models import MODELS
    from netepu.pipeline.subject_keypoints import invert_export

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model, config = load_geometry_model(MODELS / "biped.pt")
        scene, export = _hand_made_export(tmp_path, model, config["netepu"])
        refits = 0
        for warm in (0, 3):
            out = {}
            for workers in (1, 2):
                folder = tmp_path / f"w{warm}_{workers}"
                summary = invert_export(export, scene, MODELS / "biped.pt", folder,
                                        frame_step=1, steps=4, templates=2, warm_steps=warm,
                                        workers=workers, heading_tolerance=1.25)
                assert summary["subject_frames"] == 4
                refits += summary["heading_refits"]
                with np.load(folder / "keypoints3d.npz") as z:
                    out[workers] = {k: z[k] for k in z.files}
            assert out[1].keys() == out[2].keys()
            for k in out[1]:
                np.testing.assert_allclose(out[1][k], out[2][k], atol=1e-3, err_msg=k)
        assert refits > 0  # the refits ran in the workers too
    finally:
        torch.set_num_threads(threads)


def test_a_subject_frame_inverted_alone_gets_the_fit_it_gets_among_all(tmp_path):
    """``only`` (the chosen body's full fit in a run of two species) inverts the subject-frames
    given, each to the keypoints and loss it gets when every subject-frame is inverted (its
    first fit: the heading's refits, off here, see the neighbours selected)."""
    from netepu.geometry.model import load_geometry_model
    from netepu.pipeline.species_models import MODELS
    from netepu.pipeline.subject_keypoints import invert_export

    model, config = load_geometry_model(MODELS / "biped.pt")
    scene, export = _hand_made_export(tmp_path, model, config["netepu"])
    got = {}
    for name, only in (("all", None), ("some", {(1, 0), (0, 1)}), ("none", set())):
        invert_export(export, scene, MODELS / "biped.pt", tmp_path / name, frame_step=1,
                      steps=4, templates=2, only=only, heading_tolerance=0)
        with np.load(tmp_path / name / "keypoints3d.npz") as z:
            got[name] = {(int(t), int(s)): (kp, loss) for t, s, kp, loss in zip(
                z["subject_frame"], z["subject_id"], z["subject_keypoints"], z["subject_loss"],
                strict=True)}
    assert len(got["all"]) == 4 and set(got["some"]) == {(1, 0), (0, 1)} and not got["none"]
    for key, (kp, loss) in got["some"].items():
        np.testing.assert_allclose(kp, got["all"][key][0], atol=1e-5)
        assert loss == pytest.approx(got["all"][key][1], rel=1e-5)


def test_an_initialiser_of_another_body_or_no_initialiser_is_refused(tmp_path):
    """An initialiser made for other keypoints, or a file that is none, stops the stage with
    the key to change before any inversion."""
    import pytest

    from netepu.geometry.initialiser import InitialiserConfig, PoseInitialiser
    from netepu.geometry.model import load_geometry_model
    from netepu.pipeline.species_models import MODELS
    from netepu.pipeline.subject_keypoints import invert_export
    from nsd.core.atomic import atomic_save_torch
    from nsd.core.errors import ConfigError

    model, config = load_geometry_model(MODELS / "biped.pt")
    scene, export = _hand_made_export(tmp_path, model, config["netepu"])
    cfg = InitialiserConfig(n_keypoints=25, radius=1.1, grid=16, width=8)
    atomic_save_torch({"format": "netepu-initialiser-v1", "config": cfg.to_dict(),
                       "state": PoseInitialiser(cfg).state_dict()}, tmp_path / "cow.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    for path, says in ((tmp_path / "cow.pt", "made for 25 keypoints"),
                       (tmp_path / "junk.pt", "junk.pt")):
        with pytest.raises(ConfigError, match=r"netepu\.keypoints\.initialiser") as e:
            invert_export(export, scene, MODELS / "biped.pt", tmp_path / "out", frame_step=1,
                          steps=4, templates=2, initialiser=path)
        assert says in str(e.value)
        assert not (tmp_path / "out" / "keypoints3d.npz").exists()


def test_every_built_in_species_has_its_automatic_settings():
    """``auto`` keypoint settings exist for every species a built-in model is made for, and
    are values the keys accept."""
    from netepu.pipeline.species_models import builtin_models
    from netepu.pipeline.subject_keypoints import AUTO, _auto

    assert set(AUTO) == set(builtin_models())
    for species, values in AUTO.items():
        assert isinstance(values["init_templates"], int) and values["init_templates"] >= 0
        assert values["travel_speed"] >= 0
        assert _auto("travel_speed", "auto", species) == values["travel_speed"]
        assert _auto("travel_speed", 1.5, species) == 1.5
        assert values["heading_tolerance"] >= 0
    assert AUTO["biped"]["travel_speed"] > 0  # front and back from the travel: bipeds
    assert AUTO["quadruped"]["heading_tolerance"] > 0  # from the track: quadrupeds


def test_the_template_settings_beside_a_learned_start_reach_the_inversions(tmp_path, monkeypatch):
    """``init_poses`` and ``init_points_per_view`` (config keys of ``nsd-run``) are the
    settings every inversion gets; and every ``netepu.keypoints`` key that names a parameter of
    :func:`invert_export` is passed on by the stage (none silently dropped)."""
    import inspect
    from pathlib import Path

    from omegaconf import OmegaConf

    import netepu.pipeline.subject_keypoints as sk
    from netepu.geometry.model import load_geometry_model
    from netepu.pipeline.species_models import MODELS
    from netepu.pipeline.stages import _INVERSE_KEYS

    model, config = load_geometry_model(MODELS / "biped.pt")
    scene, export = _hand_made_export(tmp_path, model, config["netepu"])
    seen = []
    real = sk.invert_silhouettes

    def spy(*args, **kwargs):
        seen.append(args[4])  # (model, masks, camera, templates, settings, ...)
        return real(*args, **kwargs)

    monkeypatch.setattr(sk, "invert_silhouettes", spy)
    sk.invert_export(export, scene, MODELS / "biped.pt", tmp_path / "out", frame_step=1,
                     steps=2, templates=2, max_subject_frames=2, init_poses=16,
                     init_points_per_view=384)
    assert len(seen) == 2
    assert all(s.init_poses == 16 and s.init_points_per_view == 384 for s in seen)
    conf = OmegaConf.load(Path(__file__).parents[3] / "conf" / "run.yaml").netepu.keypoints
    params = set(inspect.signature(sk.invert_export).parameters)
    assert {"init_poses", "init_points_per_view"} <= set(_INVERSE_KEYS)
    assert {key for key in conf if key in params} - {"workers", "initialiser"} == set(
        _INVERSE_KEYS)


def test_a_refit_turned_to_its_track_is_kept_only_within_the_tolerance(tmp_path):
    """The hand-made export's fits that face away from their track are refitted: at a
    tolerance nothing can meet, every fit stays as without the check; at one everything meets,
    exactly the refitted subject-frames change. conf/run.yaml holds invert_export's default."""
    import inspect
    from pathlib import Path

    from omegaconf import OmegaConf

    from netepu.geometry.model import load_geometry_model
    from netepu.pipeline.species_models import MODELS
    from netepu.pipeline.subject_keypoints import invert_export

    model, config = load_geometry_model(MODELS / "biped.pt")
    scene, export = _hand_made_export(tmp_path, model, config["netepu"])
    got, summary = {}, {}
    for name, tolerance in (("off", 0.0), ("never", 1e-9), ("always", 1e9)):
        summary[name] = invert_export(export, scene, MODELS / "biped.pt", tmp_path / name,
                                      frame_step=1, steps=4, templates=2,
                                      heading_tolerance=tolerance)
        with np.load(tmp_path / name / "keypoints3d.npz") as z:
            got[name] = {(int(t), int(s)): kp for t, s, kp in zip(
                z["subject_frame"], z["subject_id"], z["subject_keypoints"], strict=True)}
    refits = summary["always"]["heading_refits"]
    assert summary["off"]["heading_refits"] == 0 and refits > 0
    assert summary["never"]["heading_refits"] == refits and summary["never"]["heading_turned"] == 0
    assert summary["always"]["heading_turned"] == refits
    for key, kp in got["off"].items():
        np.testing.assert_array_equal(got["never"][key], kp)
    changed = [k for k in got["off"] if not np.allclose(got["always"][k], got["off"][k])]
    assert len(changed) == refits
    conf = OmegaConf.load(Path(__file__).parents[3] / "conf" / "run.yaml").netepu.keypoints
    default = inspect.signature(invert_export).parameters["heading_tolerance"].default
    assert conf.heading_tolerance == default


@pytest.mark.parametrize("bad", ["often", -1.0, float("nan"), None])
def test_a_bad_heading_tolerance_is_refused_before_any_work(tmp_path, bad):
    from netepu.pipeline.subject_keypoints import invert_export
    from nsd.core.errors import ConfigError

    with pytest.raises(ConfigError, match="heading_tolerance"):
        invert_export(tmp_path / "no-export", tmp_path / "no-scene", tmp_path / "no.pt",
                      tmp_path / "out", heading_tolerance=bad)
    assert not (tmp_path / "out").exists()
