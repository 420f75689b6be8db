"""MOT metrics of an export (nsd/evaluation/tracking.py) on hand-built sequences."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nsd.evaluation.tracking import hota, tracking_metrics
from nsd.io.mot import read_mot, write_identity_tracks

A, B = [10.0, 10.0, 20.0, 30.0], [60.0, 10.0, 20.0, 30.0]


def _write(tmp_path, gt_rows, pred_rows):
    """rows: (camera, frame, id, box); gt ids go to identity_id, predicted to subject_id."""
    def coco(rows, key):
        images = sorted({(c, t) for c, t, _, _ in rows})
        ids = {k: i + 1 for i, k in enumerate(images)}
        return {"images": [{"id": ids[k], "camera": k[0], "frame": k[1]} for k in images],
                "annotations": [{"id": n + 1, "image_id": ids[(c, t)], key: i, "bbox": box,
                                 "area": box[2] * box[3]}
                                for n, (c, t, i, box) in enumerate(rows)]}
    (tmp_path / "scene" / "gt").mkdir(parents=True)
    (tmp_path / "export").mkdir()
    (tmp_path / "scene" / "gt" / "coco.json").write_text(json.dumps(coco(gt_rows, "identity_id")))
    (tmp_path / "export" / "subjects.coco.json").write_text(
        json.dumps(coco(pred_rows, "subject_id")))
    return tmp_path / "export", tmp_path / "scene"


def test_a_swap_costs_two_switches_and_a_third_of_idf1(tmp_path):
    """Two individuals over 3 frames; the tracks swap in frame 2: 2 ID switches, so
    MOTA = 1 - 2/6, and the best one-to-one id matching keeps 4 of 6 boxes: IDF1 = 4/6."""
    gt = [("c0", t, i, box) for t in range(3) for i, box in ((0, A), (1, B))]
    pred = [("c0", t, 1, A) for t in (0, 1)] + [("c0", t, 2, B) for t in (0, 1)]
    pred += [("c0", 2, 1, B), ("c0", 2, 2, A)]
    m = tracking_metrics(*_write(tmp_path, gt, pred))
    assert m["id_switches"] == 2
    assert m["mota"] == pytest.approx(1 - 2 / 6)
    assert m["idf1"] == pytest.approx(4 / 6)
    assert m["recall"] == m["precision"] == 1.0 and m["motp_iou"] == pytest.approx(1.0)


def test_a_miss_and_a_false_box_count_in_mota(tmp_path):
    gt = [("c0", 0, 0, A), ("c0", 1, 0, A)]
    pred = [("c0", 0, 1, A), ("c0", 1, 1, [200.0, 200.0, 5.0, 5.0])]  # frame 1: wrong place
    m = tracking_metrics(*_write(tmp_path, gt, pred))
    assert m["mota"] == pytest.approx(1 - 2 / 2)  # 1 miss + 1 false positive over 2 truths
    assert m["recall"] == pytest.approx(0.5) and m["precision"] == pytest.approx(0.5)


def test_identities_across_cameras_replace_the_tracks(tmp_path):
    """Per-camera tracks swap; the final identities (one id per individual) do not."""
    gt = [(c, t, i, box) for c in ("c0", "c1") for t in range(2) for i, box in ((0, A), (1, B))]
    pred = [("c0", 0, 1, A), ("c0", 0, 2, B), ("c0", 1, 2, A), ("c0", 1, 1, B),
            ("c1", 0, 1, A), ("c1", 0, 2, B), ("c1", 1, 1, A), ("c1", 1, 2, B)]
    export, scene = _write(tmp_path, gt, pred)
    by_box = {n + 1: (0 if box == A else 1) for n, (_, _, _, box) in enumerate(pred)}
    assert tracking_metrics(export, scene)["id_switches"] == 2
    assert tracking_metrics(export, scene, by_box)["id_switches"] == 0
    counts = write_identity_tracks(export, by_box, tmp_path / "tracks")
    assert counts == {"c0": 4, "c1": 4}
    mot = read_mot(tmp_path / "tracks" / "c0.txt")
    assert sorted(mot[mot[:, 0] == 2][:, 1]) == [1, 2]  # frame 1 (MOT: 2) holds ids 1 and 2
    assert mot[(mot[:, 0] == 2) & (mot[:, 1] == 1)][0, 2] == A[0] + 1  # identity 0 is box A


def _one_track(ids: list[int], iou: float = 1.0) -> dict:
    """One ground-truth individual over len(ids) frames, tracked under ``ids`` per frame."""
    return {"gt_ids": [[0]] * len(ids), "tracker_ids": [[i] for i in ids],
            "similarity": [np.array([[iou]])] * len(ids)}


def test_hota_known_values():
    """Perfect tracking: 1. One switch halfway: every match's association is 1/2
    (TPA = FNA = T/2), DetA 1, so HOTA = sqrt(1/2). A missed half: DetA = AssA = 1/2."""
    assert hota([_one_track([5] * 8)]) == pytest.approx({"hota": 1.0, "deta": 1.0, "assa": 1.0})
    switch = hota([_one_track([1] * 4 + [2] * 4)])
    assert switch["deta"] == pytest.approx(1.0) and switch["assa"] == pytest.approx(0.5)
    assert switch["hota"] == pytest.approx(np.sqrt(0.5))
    half = _one_track([3] * 8)
    half["tracker_ids"] = [[3]] * 4 + [[]] * 4
    half["similarity"] = [np.array([[1.0]])] * 4 + [np.zeros((1, 0))] * 4
    got = hota([half])
    assert got["deta"] == pytest.approx(0.5) and got["assa"] == pytest.approx(0.5)
    pooled = hota([_one_track([5] * 8), _one_track([1] * 4 + [2] * 4)])  # sequences combined
    assert switch["hota"] < pooled["hota"] < 1.0


def test_hota_without_trackeval_is_nan_and_said(monkeypatch, caplog):
    import builtins

    real = builtins.__import__

    def no_trackeval(name, *a, **kw):
        if name.startswith("trackeval"):
            raise ImportError(name)
        return real(name, *a, **kw)

    monkeypatch.setattr(builtins, "__import__", no_trackeval)
    got = hota([_one_track([1, 1])])
    assert all(np.isnan(v) for v in got.values()) and "TrackEval" in caplog.text
