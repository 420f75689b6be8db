"""A user's labels (nsd/io/labels.py) and an export scored against them
(nsd/evaluation/labelled.py): files written by the tools' conventions read back exactly,
known scores on a synthetic scene's ground truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import sleap_io as sio

from nsd.cameras.calibration_io import read_calibration
from nsd.core.errors import ConfigError
from nsd.evaluation.labelled import score_labels
from nsd.io.labels import read_labels_2d, read_labels_3d, read_pose_labels, triangulate_labels

CAMS = ["cam0", "cam1", "cam2"]


def _slp(world, path):
    """The visible 2D keypoints as SLEAP user instances, one video per camera folder."""
    K = next(iter(next(iter(world["points"].values())).values())).shape[0]
    skeleton = sio.Skeleton([f"kp{k}" for k in range(K)])
    videos = {c: sio.Video(filename=sorted(str(p) for p in (world["scene"] / c).glob("*.png")))
              for c in CAMS}
    tracks = {n: sio.Track(name=n) for n in ("id0", "id1")}
    frames = [sio.LabeledFrame(video=videos[c], frame_idx=f, instances=[
        sio.Instance.from_numpy(xy, skeleton=skeleton, track=tracks[n])
        for n, xy in who.items()]) for (c, f), who in sorted(world["points"].items())]
    sio.save_slp(sio.Labels(labeled_frames=frames, videos=list(videos.values()),
                            skeletons=[skeleton], tracks=list(tracks.values())), str(path))
    return path


def test_sleap_labels_read_back(world):
    labels = read_labels_2d(_slp(world, world["root"] / "l.slp"), CAMS)
    assert labels.tracked and set(labels.points) == set(world["points"])
    for key, who in world["points"].items():
        for name, xy in who.items():
            np.testing.assert_allclose(labels.points[key][name], xy, atol=1e-9)


def test_deeplabcut_table_reads_back(world, tmp_path):
    """A multi-animal CollectedData CSV (4 header rows, DeepLabCut >= 2.3's 3-column index)."""
    bodyparts = [f"kp{k}" for k in range(17)]
    cols = pd.MultiIndex.from_tuples(
        [("me", n, b, c) for n in ("id0", "id1") for b in bodyparts for c in ("x", "y")],
        names=["scorer", "individuals", "bodyparts", "coords"])
    keys = sorted(k for k in world["points"] if k[0] == "cam1")
    index = pd.MultiIndex.from_tuples([("labeled-data", c, f"img{f:04d}.png") for c, f in keys])
    data = [[world["points"][k].get(n, np.full((17, 2), np.nan))[b, j]
             for n in ("id0", "id1") for b in range(17) for j in range(2)] for k in keys]
    pd.DataFrame(data, index=index, columns=cols).to_csv(tmp_path / "CollectedData_me.csv")
    labels = read_labels_2d(tmp_path / "CollectedData_me.csv", CAMS)
    assert labels.bodyparts == bodyparts and set(labels.points) == set(keys)
    for k in keys:
        for name, xy in world["points"][k].items():
            np.testing.assert_allclose(labels.points[k][name], xy, atol=1e-9)


def test_scores_of_the_ground_truth_and_of_swapped_identities(world):
    labels = read_labels_2d(_slp(world, world["root"] / "s.slp"), CAMS)
    got = score_labels(world["export"], labels)
    assert got["detected"] == 1.0 and got["cross_view_identity"] == 1.0
    assert got["keypoints_in_mask"] > 0.9  # visible keypoints lie in the visible masks
    # identities swapped in one camera: every cross-camera pair with it is wrong
    rows = {a["id"]: (1 - a["identity_id"] if a["camera"] == "cam2" else a["identity_id"])
            for a in world["coco"]["annotations"]}
    swapped = score_labels(world["export"], labels, rows)
    per_frame = {}
    for (c, f), who in labels.points.items():
        per_frame.setdefault(f, []).extend((c, n) for n in who)
    pairs = wrong = 0
    for insts in per_frame.values():
        for i, (ca, _) in enumerate(insts):
            for cb, _ in insts[i + 1:]:
                if ca != cb:
                    pairs += 1
                    wrong += "cam2" in (ca, cb)
    assert swapped["cross_view_pairs"] == pairs
    assert swapped["cross_view_identity"] == pytest.approx(1 - wrong / pairs)
    assert swapped["keypoints_in_mask"] == got["keypoints_in_mask"]  # masks unchanged


def test_labels_name_what_is_wrong(world, tmp_path):
    with pytest.raises(ConfigError, match=r"none of the scene's cameras"):
        read_labels_2d(_slp(world, tmp_path / "x.slp"), ["left", "right"])
    with pytest.raises(ConfigError, match="does not exist"):
        read_labels_2d(tmp_path / "missing.slp", CAMS)
    (tmp_path / "l.txt").write_text("x")
    with pytest.raises(ConfigError, match="unknown format"):
        read_labels_2d(tmp_path / "l.txt", CAMS)


def test_anipose_3d_labels_in_millimetres(tmp_path):
    xyz = np.arange(2 * 3 * 3, dtype=float).reshape(2, 3, 3) * 100.0  # frames, bodyparts, xyz
    cols = {}
    for k, b in enumerate(("nose", "tail", "paw")):
        for j, c in enumerate("xyz"):
            cols[f"{b}_{c}"] = xyz[:, k, j]
        cols[f"{b}_error"] = [0.5, 0.5]
    cols["fnum"] = [7, 9]
    df = pd.DataFrame(cols)
    df.loc[1, "tail_y"] = np.nan  # an incomplete pose is left out
    df.to_csv(tmp_path / "pose3d.csv", index=False)
    labels = read_labels_3d(tmp_path / "pose3d.csv", "mm")
    assert labels.bodyparts == ["nose", "tail", "paw"] and list(labels.frames) == [7]
    np.testing.assert_allclose(labels.keypoints3d(7)[0], xyz[0] / 1000.0)
    assert labels.keypoints3d(9) == {} and labels.num_keypoints == 3
    with pytest.raises(ConfigError, match="units 'ft'"):
        read_labels_3d(tmp_path / "pose3d.csv", "ft")


def test_2d_labels_triangulate_to_the_3d_keypoints(world):
    """SLEAP labels of the visible keypoints in 3 cameras, triangulated with the scene's
    calibration, give the ground truth's 3D keypoints (poses with a keypoint seen by fewer
    than two cameras are left out), and read_pose_labels dispatches to it."""
    rig = read_calibration(world["scene"])
    labels = read_pose_labels(_slp(world, world["root"] / "t.slp"), rig)
    with np.load(world["scene"] / "gt" / "keypoints3d.npz") as z:
        truth = {int(k.split("_")[1]): z[k] for k in z.files}
    assert len(labels.frames) > 0 and labels.num_keypoints == 17
    n = 0
    for f in labels.frames:
        for i, pose in labels.keypoints3d(f).items():  # i: index of the track name id0, id1
            np.testing.assert_allclose(pose, truth[i][f], atol=2e-3)  # 2D labels to 1e-4 px
            n += 1
    assert n >= 2
    with pytest.raises(ConfigError, match="named across cameras"):
        untracked = read_labels_2d(_slp(world, world["root"] / "u.slp"), CAMS)
        untracked.tracked = False
        triangulate_labels(untracked, rig)


def test_single_animal_deeplabcut_table_with_a_one_column_index(tmp_path):
    """Older DeepLabCut: 3 header rows (scorer, bodyparts, coords), the image path as one
    index column; the camera is the folder the table sits in when the path names none."""
    cols = pd.MultiIndex.from_tuples([("me", b, c) for b in ("nose", "tail") for c in "xy"],
                                     names=["scorer", "bodyparts", "coords"])
    table = pd.DataFrame([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, np.nan, np.nan]],
                         index=["labeled-data/cam2/img0007.png", "img0011.png"], columns=cols)
    (tmp_path / "cam2").mkdir()
    table.to_csv(tmp_path / "cam2" / "CollectedData_me.csv")
    labels = read_labels_2d(tmp_path / "cam2" / "CollectedData_me.csv", CAMS)
    assert not labels.tracked and labels.bodyparts == ["nose", "tail"]
    np.testing.assert_allclose(labels.points[("cam2", 7)]["individual"], [[1, 2], [3, 4]])
    got = labels.points[("cam2", 11)]["individual"]
    np.testing.assert_allclose(got[0], [5, 6])
    assert np.isnan(got[1]).all()  # an unlabelled keypoint

