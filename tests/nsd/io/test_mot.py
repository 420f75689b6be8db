"""MOTChallenge files: the written lines parse back to the same boxes; bad files are named."""

from __future__ import annotations

import numpy as np
import pytest

from nsd.io.mot import MOT_COLUMNS, MotWriter, format_mot_line, read_mot


def test_write_then_read_round_trip(tmp_path):
    boxes = {
        ("a", 0, 1): [0.0, 0.0, 10.0, 20.0],
        ("a", 1, 1): [2.5, 3.0, 10.0, 20.0],
        ("a", 1, 2): [40.0, 8.0, 5.0, 6.0],
    }
    with MotWriter(tmp_path, ["a", "b"]) as w:
        for (cam, t, tid), box in boxes.items():
            w.write(cam, t, tid, box, 0.5 + 0.1 * tid)
    assert w.counts == {"a": 3, "b": 0}
    rows = read_mot(tmp_path / "a.txt")
    assert rows.shape == (3, len(MOT_COLUMNS))
    for row, ((_, t, tid), box) in zip(rows, boxes.items(), strict=True):
        assert row[0] == t + 1 and row[1] == tid  # 1-based frames
        np.testing.assert_allclose(row[2:4], np.asarray(box[:2]) + 1)  # 1-based pixels
        np.testing.assert_allclose(row[4:6], box[2:])
        assert row[6] == pytest.approx(0.5 + 0.1 * tid)
        assert (row[7:] == -1).all()
    assert read_mot(tmp_path / "b.txt").shape == (0, 10)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1,1,1,1,2,2,1\n", "7 values"),
        ("1,x,1,1,2,2,1,-1,-1,-1\n", "not numbers"),
        ("0,1,1,1,2,2,1,-1,-1,-1\n", "frame and id must be >= 1"),
        ("1,1,1,1,2,2,1,-1,-1,-1\n1,1,5,5,2,2,1,-1,-1,-1\n", "track 1 twice in frame 1"),
    ],
)
def test_read_mot_names_the_bad_line(tmp_path, text, match):
    path = tmp_path / "seq.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as e:
        read_mot(path)
    assert "seq.txt:" in str(e.value)


def test_track_ids_must_be_positive():
    with pytest.raises(ValueError, match="positive"):
        format_mot_line(0, 0, [0, 0, 1, 1], 1.0)
