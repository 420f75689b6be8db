"""identities.csv: written and read back column by column."""

from __future__ import annotations

import numpy as np

from nsd.io.identities import COLUMNS, read_identities, write_identities


def test_identities_round_trip_with_awkward_camera_names(tmp_path):
    cols = {"id": [3, 1, 2], "camera": ["cam,0", "cam 1", 'c"2'], "frame": [0, 0, 7],
            "subject_id": [1, 2, 1], "identity": [0, -1, 1]}
    write_identities(tmp_path / "identities.csv", cols)
    back = read_identities(tmp_path / "identities.csv")
    assert list(back) == list(COLUMNS)
    for c in COLUMNS:
        assert back[c].tolist() == cols[c], c
    assert back["identity"].dtype == np.int64
    assert (tmp_path / "identities.csv").read_text().splitlines()[0] == ",".join(COLUMNS)
