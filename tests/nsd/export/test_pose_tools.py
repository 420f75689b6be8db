"""World positions and the pose tools' files (nsd/export/positions.py, nsd/export/pose_tools.py):
known positions triangulated back, every file read back by its own library."""

from __future__ import annotations

import json
import shutil

import ezc3d
import numpy as np
import pandas as pd
import pytest
import sleap_io as sio
from ndx_pose import PoseEstimation
from pycocotools import mask as mask_utils
from pynwb import NWBHDF5IO

from nsd.cameras.calibration import CameraRig
from nsd.cameras.calibration_io import read_calibration
from nsd.export.pose_tools import read_trc, write_pose_tool_files
from nsd.export.positions import (
    mask_centroids,
    read_positions,
    triangulate_positions,
    write_positions,
)
from nsd.io.mot import read_mot, write_identity_tracks


def _square(uv: np.ndarray, size: tuple[int, int], half: int = 2) -> dict:
    """RLE of a (2 half + 1)-pixel square centred on the pixel nearest ``uv``."""
    m = np.zeros((size[1], size[0]), np.uint8, order="F")
    x, y = (round(v) for v in uv)
    m[y - half:y + half + 1, x - half:x + half + 1] = 1
    rle = mask_utils.encode(m)
    rle["counts"] = rle["counts"].decode()
    return rle


def test_known_positions_are_triangulated_back(random_cameras, tmp_path):
    """Points seen by 6 distorted cameras: the centroids of masks around their projections
    (rounded to pixels) give back the points within the rounding's reach."""
    rig = CameraRig(random_cameras)
    points = {(0, 0): np.array([0.3, -0.2, 0.5]), (0, 1): np.array([-0.4, 0.1, 0.9]),
              (1, 0): np.array([0.0, 0.5, 0.2])}
    anns, images = [], []
    for (frame, ident), X in points.items():
        for c in rig:
            uv = c.project(X[None])[0][0]
            images.append({"id": len(images) + 1, "camera": c.name, "frame": frame})
            anns.append({"id": len(anns) + 1, "image_id": len(images), "camera": c.name,
                         "frame": frame, "subject_id": ident + 1,
                         "segmentation": _square(uv, c.size), "bbox": [0, 0, 1, 1]})
    (tmp_path / "subjects.coco.json").write_text(json.dumps({"images": images,
                                                             "annotations": anns}))
    ids = {a["id"]: a["subject_id"] - 1 for a in anns}
    got = triangulate_positions(tmp_path, rig, ids)
    assert set(got) == set(points)
    for key, X in points.items():
        np.testing.assert_allclose(got[key][0], X, atol=0.01)  # 0.5 px at ~5 m, f >= 200
        assert got[key][1] == len(rig)
    one_view = {a["id"]: (ids[a["id"]] if a["camera"] == "cam0" else -1) for a in anns}
    assert triangulate_positions(tmp_path, rig, one_view) == {}  # one view: no position
    cents = mask_centroids({"annotations": anns})  # shared: the same positions, no decode
    again = triangulate_positions(tmp_path, rig, ids, centroids=cents)
    assert all(np.array_equal(again[key][0], got[key][0]) for key in got)
    assert triangulate_positions(tmp_path, rig, ids, centroids={}) == {}  # only those given
    write_positions(tmp_path / "positions.csv", got)
    back = read_positions(tmp_path / "positions.csv")
    for key in got:
        np.testing.assert_allclose(back[key][0], got[key][0], atol=1e-6)


@pytest.fixture(scope="module")
def gt_export(world, tmp_path_factory):
    """The shared synthetic world's ground truth as an export (masks, boxes, identities)
    written in every pose-tool format, so that every file can be checked against known
    values."""
    scene, export, coco = world["scene"], world["export"], world["coco"]
    out = tmp_path_factory.mktemp("formats") / "formats"
    rig = read_calibration(scene)
    row_ids = {a["id"]: a["identity_id"] for a in coco["annotations"]}
    positions = triangulate_positions(export, rig, row_ids)
    summary = write_pose_tool_files(export, scene, rig, out, row_ids, positions)
    return {"scene": scene, "export": export, "coco": coco, "rig": rig, "row_ids": row_ids,
            "positions": positions, "out": out, "summary": summary}


def test_positions_of_the_ground_truth_are_near_the_bodies(gt_export):
    """Visible-mask centroids triangulated: within 0.25 m of the mean of the individual's 3D
    keypoints (a centroid of what a camera sees is not the body's centre)."""
    with np.load(gt_export["scene"] / "gt" / "keypoints3d.npz") as z:
        kp = {int(k.split("_")[1]): z[k] for k in z.files}  # identity -> (T, K, 3)
    pos = gt_export["positions"]
    assert len(pos) >= len(kp[0])
    errors = [np.linalg.norm(xyz - kp[i][f].mean(0)) for (f, i), (xyz, _) in pos.items()]
    assert np.median(errors) < 0.25, errors


def test_sleap_file_holds_every_row(gt_export):
    coco, rig = gt_export["coco"], gt_export["rig"]
    labels = sio.load_slp(str(gt_export["out"] / "subjects.slp"))
    n_rows = sum(1 for a in coco["annotations"] if mask_utils.area(a["segmentation"]) > 0)
    assert sum(len(lf.instances) for lf in labels.labeled_frames) == n_rows
    assert sorted(t.name for t in labels.tracks) == ["id0", "id1"]
    assert len(labels.masks) == len(labels.bboxes) == len(coco["annotations"])
    centroids = mask_centroids(coco)
    by_key = {(a["camera"], a["frame"], a["identity_id"]): a for a in coco["annotations"]}
    cams = [c.name for c in rig]
    for lf in labels.labeled_frames:
        cam = cams[labels.videos.index(lf.video)]
        for inst in lf.instances:
            a = by_key[(cam, lf.frame_idx, int(inst.track.name[2:]))]
            np.testing.assert_allclose(inst.numpy()[0], centroids[a["id"]], atol=1e-6)
    lf = labels.labeled_frames[0]
    a = by_key[(cams[labels.videos.index(lf.video)], lf.frame_idx,
                int(lf.masks[0].track.name[2:]))]
    assert np.array_equal(lf.masks[0].data.astype(bool),
                          mask_utils.decode(a["segmentation"]).astype(bool))
    session = labels.sessions[0]
    np.testing.assert_allclose(session.camera_group.cameras[1].matrix, rig[1].K)


def test_nwb_file_holds_a_pose_series_per_camera_and_track(gt_export):
    with NWBHDF5IO(str(gt_export["out"] / "subjects.nwb"), "r") as io:
        nwb = io.read()
        series = [obj for obj in nwb.objects.values() if isinstance(obj, PoseEstimation)]
        assert len(series) == 3 * 2  # cameras x tracks
        for pe in series:
            (node,) = pe.pose_estimation_series.values()
            data = np.asarray(node.data)
            assert data.shape[1] == 2 and np.isfinite(data).any()
    labels = sio.load_nwb(str(gt_export["out"] / "subjects.nwb"))  # and sleap-io reads it
    assert sum(len(lf.instances) for lf in labels.labeled_frames) == gt_export["summary"][
        "instances"]


def test_deeplabcut_tables_hold_the_centroids(gt_export):
    coco, centroids = gt_export["coco"], mask_centroids(gt_export["coco"])
    table = pd.read_csv(gt_export["out"] / "dlc" / "cam1.csv", header=[0, 1, 2, 3], index_col=0)
    rows = [a for a in coco["annotations"] if a["camera"] == "cam1" and a["id"] in centroids]
    for a in rows:
        row = table.iloc[next(i for i, name in enumerate(table.index)
                          if name.endswith(f"img{a['frame']:04d}.png"))]
        x = row[("nsd-netepu", f"id{a['identity_id']}", "centroid", "x")]
        y = row[("nsd-netepu", f"id{a['identity_id']}", "centroid", "y")]
        np.testing.assert_allclose([x, y], centroids[a["id"]], atol=1e-6)


def test_trc_and_c3d_hold_the_positions(gt_export):
    pos = gt_export["positions"]
    names, frames, pts, rate = read_trc(gt_export["out"] / "trajectories.trc")
    assert names == ["id0", "id1"] and rate == pytest.approx(gt_export["summary"]["fps"])
    c3d = ezc3d.c3d(str(gt_export["out"] / "trajectories.c3d"))
    assert c3d["parameters"]["POINT"]["LABELS"]["value"] == names
    c3d_pts = c3d["data"]["points"][:3].transpose(2, 1, 0)  # (F, M, 3)
    for (f, i), (xyz, _) in pos.items():
        row = int(np.flatnonzero(frames == f)[0])
        np.testing.assert_allclose(pts[row, i], xyz, atol=1e-6)
        np.testing.assert_allclose(c3d_pts[row, i], xyz, atol=1e-5)  # float32 in the file
    missing = np.isnan(pts).any(-1)
    assert np.array_equal(missing, np.isnan(c3d_pts).any(-1))


def test_mot_tracks_carry_identities_and_world_positions(gt_export, tmp_path):
    counts = write_identity_tracks(gt_export["export"], gt_export["row_ids"], tmp_path,
                                   gt_export["positions"])
    assert sum(counts.values()) == len(gt_export["coco"]["annotations"])
    rows = read_mot(tmp_path / "cam0.txt")
    for r in rows:
        key = (int(r[0]) - 1, int(r[1]) - 1)
        if key in gt_export["positions"]:
            np.testing.assert_allclose(r[7:10], gt_export["positions"][key][0], atol=1e-5)
        else:
            assert np.all(r[7:10] == -1)


def test_image_folders_and_unknown_formats(gt_export, tmp_path):
    with pytest.raises(ValueError, match=r"unknown.*'xls'"):
        write_pose_tool_files(gt_export["export"], gt_export["scene"], gt_export["rig"],
                              tmp_path, formats=("xls",))
    shutil.rmtree(tmp_path)
    s = write_pose_tool_files(gt_export["export"], gt_export["scene"], gt_export["rig"],
                              tmp_path, formats=("slp",))  # per-camera tracks as ids
    assert s["files"] == ["subjects.slp"] and s["tracks"] == 2


def test_an_export_without_subjects_writes_nothing_and_says_so(gt_export, tmp_path, caplog):
    """Footage in which nothing was found: no file (the tools' writers refuse empty
    labels), a warning, and a summary that says why."""
    empty = tmp_path / "export"
    empty.mkdir()
    coco = dict(gt_export["coco"], annotations=[])
    (empty / "subjects.coco.json").write_text(json.dumps(coco))
    s = write_pose_tool_files(empty, gt_export["scene"], gt_export["rig"], tmp_path / "out")
    assert s["files"] == [] and s["skipped"] == "no subjects"
    assert "no subject" in caplog.text


def test_a_camera_without_any_identified_row_still_gets_an_nwb_file(gt_export, tmp_path):
    """sleap-io's NWB writer fails on a video without instances (a real run: no subject of
    one camera got keypoints); that camera is left out of the NWB file, the others kept."""
    coco, rig = gt_export["coco"], gt_export["rig"]
    first = rig[0].name
    row_ids = {a["id"]: (-1 if a["camera"] == first else a["identity_id"])
               for a in coco["annotations"]}
    summary = write_pose_tool_files(gt_export["export"], gt_export["scene"], rig, tmp_path,
                                    row_ids, formats=("slp", "nwb"))
    with NWBHDF5IO(str(tmp_path / "subjects.nwb"), "r") as io:
        series = [o for o in io.read().objects.values() if isinstance(o, PoseEstimation)]
        assert len(series) == (len(rig) - 1) * 2  # the other cameras x tracks
    n = sum(1 for a in coco["annotations"]
            if a["camera"] != first and mask_utils.area(a["segmentation"]) > 0)
    assert summary["instances"] == n
    labels = sio.load_slp(str(tmp_path / "subjects.slp"))
    assert all(lf.instances for lf in labels.labeled_frames)  # no empty frames


def test_two_rows_of_one_identity_in_a_camera_frame_keep_the_better_one(gt_export, tmp_path,
                                                                       caplog):
    """Identities filled in from tracks can give two rows of one camera-frame the same
    identity; NWB then failed inside its writer (a duplicate index). The row of higher score
    keeps the identity, the other is left out of the tools' files, and the log says so."""
    from nsd.export.pose_tools import one_row_per_identity

    anns = [{"id": 1, "camera": "a", "frame": 0, "score": 0.5, "area": 9},
            {"id": 2, "camera": "a", "frame": 0, "score": 0.9, "area": 4},
            {"id": 3, "camera": "a", "frame": 0, "score": 0.9, "area": 4},  # tie: lower id
            {"id": 4, "camera": "b", "frame": 0, "score": 0.1, "area": 1},  # another camera
            {"id": 5, "camera": "a", "frame": 1, "score": 0.1, "area": 1}]  # another frame
    got, lost = one_row_per_identity(anns, {1: 0, 2: 0, 3: 0, 4: 0, 5: 0, 6: -1})
    assert got == {1: -1, 2: 0, 3: -1, 4: 0, 5: 0, 6: -1} and lost == 2
    coco, rig = gt_export["coco"], gt_export["rig"]
    row_ids = {a["id"]: 0 for a in coco["annotations"]}  # every row one identity
    summary = write_pose_tool_files(gt_export["export"], gt_export["scene"], rig, tmp_path,
                                    row_ids, formats=("slp", "nwb"))
    frames = {(a["camera"], a["frame"]) for a in coco["annotations"]}
    assert summary["rows_left_out"] == len(coco["annotations"]) - len(frames)
    assert summary["instances"] <= len(frames) and "share their identity" in caplog.text
    with NWBHDF5IO(str(tmp_path / "subjects.nwb"), "r") as io:
        assert any(isinstance(o, PoseEstimation) for o in io.read().objects.values())


@pytest.fixture(scope="module")
def two_skeletons(gt_export, tmp_path_factory):
    """The ground truth's keypoints as two keypoint files: identity 0 on the biped's named
    skeleton, identity 1 on a 5-node skeleton of no species (a scene of two species),
    written in every format."""
    from nsd.export.pose_tools import KeypointFile
    from nsd.synth.skeleton import BIPED

    coco, root = gt_export["coco"], tmp_path_factory.mktemp("two_skeletons")
    with np.load(gt_export["scene"] / "gt" / "keypoints3d.npz") as z:
        truth = {i: z[f"identity_{i}"] for i in (0, 1)}  # (T, K, 3)
    files, fitted = [], {}
    for i, (name, k) in enumerate([("biped", BIPED.num_keypoints), ("other", 5)]):
        rows = [a for a in coco["annotations"] if a["identity_id"] == i]
        kps = np.stack([truth[i][a["frame"], :k] for a in rows])
        np.savez(root / f"{name}.npz", id=np.array([a["id"] for a in rows]), keypoints=kps)
        fitted |= {a["id"]: kp for a, kp in zip(rows, kps, strict=True)}
        files.append(KeypointFile(root / f"{name}.npz", name, BIPED.keypoint_names,
                                  BIPED.skeleton) if i == 0 else
                     KeypointFile(root / f"{name}.npz", name))
    out = root / "formats"
    summary = write_pose_tool_files(gt_export["export"], gt_export["scene"], gt_export["rig"],
                                    out, gt_export["row_ids"], gt_export["positions"], files)
    return {"out": out, "files": files, "fitted": fitted, "summary": summary, "truth": truth}


def test_two_skeletons_each_instance_on_its_own_in_slp_and_nwb(gt_export, two_skeletons):
    """Each row's keypoints projected into its camera, on its own skeleton, in .slp; NWB
    holds both skeletons, each track's pose series on its own."""
    from nsd.synth.skeleton import BIPED

    coco, rig, out = gt_export["coco"], gt_export["rig"], two_skeletons["out"]
    by_key = {(a["camera"], a["frame"], a["identity_id"]): a for a in coco["annotations"]}
    labels = sio.load_slp(str(out / "subjects.slp"))
    assert {s.name: len(s.nodes) for s in labels.skeletons} == {
        "biped": BIPED.num_keypoints, "other": 5}
    assert labels.skeletons[0].node_names == list(BIPED.keypoint_names)
    assert len(labels.skeletons[0].edges) == len(BIPED.skeleton)
    cams, seen = [c.name for c in rig], set()
    for lf in labels.labeled_frames:
        cam = rig[cams[labels.videos.index(lf.video)]]
        for inst in lf.instances:
            ident = int(inst.track.name[2:])
            assert inst.skeleton.name == ("biped", "other")[ident]
            kp = two_skeletons["fitted"][by_key[(cam.name, lf.frame_idx, ident)]["id"]]
            uv, z = cam.project(kp)
            np.testing.assert_allclose(inst.numpy(), np.where((z > 0)[:, None], uv, np.nan),
                                       atol=1e-4)
            seen.add(ident)
    assert seen == {0, 1}
    counts = two_skeletons["summary"]["skeletons"]
    assert counts == {"biped": sum(a["identity_id"] == 0 for a in coco["annotations"]),
                      "other": sum(a["identity_id"] == 1 for a in coco["annotations"])}
    with NWBHDF5IO(str(out / "subjects.nwb"), "r") as io:
        series = [o for o in io.read().objects.values() if isinstance(o, PoseEstimation)]
        assert len(series) == len(rig) * 2  # cameras x tracks
        for pe in series:  # each track's series on its own skeleton, which it links
            own = ("biped", "other")[int(pe.name.removeprefix("track=id"))]
            assert pe.skeleton.name == own
            assert sorted(pe.pose_estimation_series) == sorted(pe.skeleton.nodes[:])
            assert len(pe.skeleton.nodes) == (BIPED.num_keypoints if own == "biped" else 5)
            data = np.asarray(next(iter(pe.pose_estimation_series.values())).data)
            assert data.shape[1] == 2 and np.isfinite(data).any()


def test_two_skeletons_give_a_deeplabcut_table_each_and_named_markers(gt_export, two_skeletons):
    """DeepLabCut takes one skeleton per table: dlc/<skeleton>/<camera>.csv; TRC and C3D
    name each identity's markers by its own skeleton's nodes and hold its keypoints."""
    from nsd.synth.skeleton import BIPED

    out, rig = two_skeletons["out"], gt_export["rig"]
    for name, parts in (("biped", BIPED.keypoint_names), ("other", ("kp0", "kp4"))):
        table = pd.read_csv(out / "dlc" / name / "cam1.csv", header=[0, 1, 2, 3], index_col=0)
        assert set(parts) <= set(table.columns.get_level_values(2))
    assert not (out / "dlc" / "cam1.csv").exists()
    names, frames, pts, _ = read_trc(out / "trajectories.trc")
    assert names == (["id0", "id1"] + [f"id0_{n}" for n in BIPED.keypoint_names]
                     + [f"id1_kp{j}" for j in range(5)])
    for i, (first, k) in enumerate([(2, BIPED.num_keypoints), (2 + BIPED.num_keypoints, 5)]):
        for row, f in enumerate(frames):
            got = pts[row, first:first + k]
            if np.isfinite(got).all():
                np.testing.assert_allclose(got, two_skeletons["truth"][i][f, :k], atol=1e-6)
        assert np.isfinite(pts[:, first:first + k]).all(-1).any()
    c3d = ezc3d.c3d(str(out / "trajectories.c3d"))
    assert c3d["parameters"]["POINT"]["LABELS"]["value"] == names
    assert len(rig) == 3


def test_keypoint_files_that_disagree_are_refused_with_the_file_named(gt_export, two_skeletons,
                                                                      tmp_path):
    from nsd.export.pose_tools import KeypointFile

    biped, other = two_skeletons["files"]
    args = (gt_export["export"], gt_export["scene"], gt_export["rig"], tmp_path)
    with pytest.raises(ValueError, match=r"other\.npz: 5 keypoints, but skeleton 'x' has 2"):
        write_pose_tool_files(*args, keypoints=[KeypointFile(other.path, "x", ("a", "b"))])
    with pytest.raises(ValueError, match=r"biped\.npz: row \d+ is also fitted on skeleton 'b'"):
        write_pose_tool_files(*args, keypoints=[KeypointFile(biped.path, "b"),
                                                KeypointFile(biped.path, "c")])
    with pytest.raises(ValueError, match="named by two keypoint files"):
        write_pose_tool_files(*args, keypoints=[biped, KeypointFile(other.path, "biped")])
