"""`open_dataset`: ok frames only, member selection, identity fields, labels and grid."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import LABELS
from nuplan_occ.storage import DatasetWriter, MissingMemberError, read_manifest
from nuplan_occ.synth.grid_frames import synthetic_log

GRID = GridSpec(-2.0, 2.0, -2.0, 2.0, -1.0, 1.0, 0.25)  # 16 x 16 x 8


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    a = synthetic_log(GRID, "log-a", 0, [3, 3], members=["semantics", "mask_camera"], failed=[1, 4])
    b = synthetic_log(GRID, "log-b", 1, [2], members=["semantics"])
    writer = DatasetWriter(str(root), {"params": {"name": "read-test"}}, grid=GRID)
    writer.commit(writer.write_shard("a", a) + writer.write_shard("b", b))
    return str(root), a + b


def test_failed_frames_are_in_the_manifest_but_not_in_the_dataset(built):
    root, records = built
    assert read_manifest(root).num_rows == 8
    ds = open_dataset(root)
    ok = [r for r in records if r.status == "ok"]
    assert len(ds) == ds.manifest.num_rows == 6
    assert set(ds.manifest["status"].to_pylist()) == {"ok"}
    assert [ds[i]["token"] for i in range(len(ds))] == [r.token for r in ok]
    failed = [r.token for r in records if r.status == "failed"]
    for token in failed:
        with pytest.raises(KeyError, match="no ok frame"):
            ds.index_of_token(token)
    assert ds.index_of_token(ok[3].token) == 3


def test_members_are_never_faked(built):
    root, records = built
    ds = open_dataset(root)
    assert set(ds[0]) == {"semantics", "mask_camera", "ego_to_global", "token", "log_name", "scene_token",
                          "timestamp_us", "frame_index"}
    assert ds.members_of(0) == ("semantics", "mask_camera") and ds.members_of(-1) == ("semantics",)
    last = ds[-1]
    assert "mask_camera" not in last and last["log_name"] == "log-b"
    with pytest.raises(MissingMemberError, match="no 'mask_camera' member"):
        ds.get(len(ds) - 1, keys=("mask_camera",))
    with pytest.raises(IndexError):
        ds[len(ds)]
    only = ds.get(2, keys=("mask_camera",))
    assert "semantics" not in only
    np.testing.assert_array_equal(only["mask_camera"], records[3].arrays["mask_camera"])


def test_dataset_exposes_grid_labels_and_metadata(built):
    ds = open_dataset(built[0])
    assert ds.grid == GRID
    assert ds.labels[12] == {"name": "road", "color": LABELS.colors[12]}
    assert set(ds.labels) == set(LABELS.names)
    assert ds.metadata["params"] == {"name": "read-test"}
    np.testing.assert_array_equal(ds[1]["ego_to_global"], built[1][2].ego_to_global)


def test_top_level_open_dataset_is_the_same_reader(built):
    import nuplan_occ

    root, records = built
    ds = nuplan_occ.open_dataset(root)
    assert len(ds) == len(open_dataset(root)) == sum(r.status == "ok" for r in records)
    assert np.array_equal(ds[0]["semantics"], open_dataset(root)[0]["semantics"])
