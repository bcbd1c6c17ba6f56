"""Round trips of every member type through shards, on small grids, the real grid and memory://."""

from __future__ import annotations

import io
import json
import tarfile
import uuid

import numpy as np
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import LABELS
from nuplan_occ.storage import MEMBERS, DatasetWriter, FrameRecord, InvalidFrameError, read_manifest, read_member
from nuplan_occ.synth.grid_frames import synthetic_arrays, synthetic_log

SMALL = GridSpec(-4.0, 4.0, -4.0, 4.0, -1.0, 1.0, 0.25)  # 32 x 32 x 8
LOG = "2021.05.12.22.00.38_veh-35_01008_01518"


def _write(root: str, records: list[FrameRecord], grid: GridSpec = SMALL, shard: str = "logs/a") -> list[dict]:
    writer = DatasetWriter(root, {"params": {"test": True}}, grid=grid)
    rows = writer.write_shard(shard, records)
    writer.commit(rows)
    return rows


def _random_arrays(grid: GridSpec, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Arrays with random content (incompressible-ish) of every member, to exercise the codecs."""
    ids = np.array(sorted(LABELS.names), dtype=np.uint8)
    return {
        "semantics": ids[rng.integers(0, len(ids), grid.shape)],
        "mask_lidar": rng.random(grid.shape) < 0.3,
        "mask_camera": rng.random(grid.shape) < 0.7,
        "instance": rng.integers(0, 65535, grid.shape, dtype=np.uint16),
        "flow": rng.normal(0, 10, (*grid.shape, 3)).astype(np.float16),
    }


def test_all_members_round_trip_small_grid(tmp_path):
    records = synthetic_log(SMALL, LOG, 3, [4, 3], members=list(MEMBERS), failed=[2])
    rng = np.random.default_rng(0)
    records[0].arrays = _random_arrays(SMALL, rng)
    rows = _write(str(tmp_path), records)
    ds = open_dataset(str(tmp_path))
    ok = [r for r in records if r.status == "ok"]
    assert len(ds) == len(ok) == 6
    for i, record in enumerate(ok):
        frame = ds[i]
        assert frame["token"] == record.token and frame["frame_index"] == record.frame_index
        assert frame["log_name"] == LOG and frame["scene_token"] == record.scene_token
        assert frame["timestamp_us"] == record.timestamp_us
        np.testing.assert_array_equal(frame["ego_to_global"], record.ego_to_global)
        for name, array in record.arrays.items():
            assert frame[name].dtype == array.dtype and frame[name].shape == array.shape
            np.testing.assert_array_equal(frame[name], array)
            assert frame[name].flags.writeable
    row = next(r for r in rows if r["token"] == ok[0].token)
    np.testing.assert_array_equal(read_member(str(tmp_path), row, "flow"), ok[0].arrays["flow"])
    hist = np.bincount(ok[0].arrays["semantics"].ravel(), minlength=256)
    assert row["class_hist"] == hist[: max(LABELS.names) + 1].tolist()


def test_real_grid_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    arrays = synthetic_arrays(DEFAULT_GRID, 0, list(MEMBERS))
    arrays["semantics"][rng.integers(0, 400, 2000), rng.integers(0, 400, 2000), rng.integers(0, 32, 2000)] = 4
    arrays["flow"][100:110, 50:60, 3:9] = rng.normal(0, 3, (10, 10, 6, 3)).astype(np.float16)
    record = synthetic_log(DEFAULT_GRID, LOG, 0, [1])[0]
    record.arrays = arrays
    rows = _write(str(tmp_path), [record], grid=DEFAULT_GRID)
    assert 0 < rows[0]["semantics_nbytes"] < 100_000
    frame = open_dataset(str(tmp_path))[0]
    assert frame["semantics"].shape == (400, 400, 32) and frame["flow"].shape == (400, 400, 32, 3)
    for name in MEMBERS:
        np.testing.assert_array_equal(frame[name], arrays[name])


def test_shard_members_follow_webdataset_naming(tmp_path):
    records = synthetic_log(SMALL, LOG, 0, [3], members=["semantics", "mask_lidar"])
    rows = _write(str(tmp_path), records, shard="a/b.c")
    data = (tmp_path / "shards" / "a" / "b.c.tar").read_bytes()
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        names = tar.getnames()
        meta = json.loads(tar.extractfile(f"{rows[1]['key']}.json").read())
        for info in tar.getmembers():
            assert info.mtime == 0 and info.uid == 0 and info.uname == ""
    keys = {name.split(".", 1)[0] for name in names}
    assert keys == {r["key"] for r in rows} == {f"{LOG.replace('.', '_')}-{i:06d}" for i in range(3)}
    assert {name.split(".", 1)[1] for name in names} == {"sem.zst", "mask_lidar.bits.xz", "json"}
    # each sample's members are contiguous, as WebDataset needs
    assert [name.split(".", 1)[0] for name in names] == sorted(name.split(".", 1)[0] for name in names)
    assert meta["token"] == records[1].token and meta["columns"]["ego_speed"] == 5.0
    assert meta["members"] == {"mask_lidar": "mask_lidar.bits.xz", "semantics": "sem.zst"}


@pytest.mark.parametrize("scheme", ["memory", "file"])
def test_url_round_trip(tmp_path, scheme):
    root = f"memory://occ-{uuid.uuid4().hex}/ds" if scheme == "memory" else f"file://{tmp_path}/ds"
    records = synthetic_log(SMALL, LOG, 0, [3], members=["semantics", "mask_camera"])
    _write(root, records)
    assert read_manifest(root).num_rows == 3
    ds = open_dataset(root)
    assert len(ds) == 3
    for i, record in enumerate(records):
        got = ds.get(i, keys=("mask_camera",))
        assert "semantics" not in got
        np.testing.assert_array_equal(got["mask_camera"], record.arrays["mask_camera"])
        np.testing.assert_array_equal(ds[i]["semantics"], record.arrays["semantics"])


def _one(**changes) -> FrameRecord:
    record = synthetic_log(SMALL, LOG, 0, [1])[0]
    for name, value in changes.items():
        setattr(record, name, value)
    return record


@pytest.mark.parametrize(
    "record, message",
    [
        (_one(arrays={"semantics": np.zeros(SMALL.shape, dtype=np.int32)}), "dtype int32"),
        (_one(arrays={"semantics": np.zeros((4, 4, 4), dtype=np.uint8)}), "shape"),
        (_one(arrays={"semantics": np.full(SMALL.shape, 9, dtype=np.uint8)}), r"ids \[9\]"),
        (_one(arrays={"lidar": np.zeros(SMALL.shape, dtype=np.uint8)}), "unknown member"),
        (_one(arrays={}), "an ok frame has semantics"),
        (_one(status="failed"), "a failed frame has no arrays"),
        (_one(columns={"token": 1}), "reserved"),
        (_one(columns={"speed": [1, 2]}), "expected a scalar"),
        (_one(ego_to_global=np.eye(3)), "ego_to_global"),
    ],
)
def test_bad_records_are_refused(tmp_path, record, message):
    writer = DatasetWriter(str(tmp_path), {"params": {}}, grid=SMALL)
    with pytest.raises(InvalidFrameError, match=message):
        writer.write_shard("s", [record])
    assert not (tmp_path / "shards").exists()


def test_bad_writer_input_is_refused(tmp_path):
    with pytest.raises(InvalidFrameError, match="params"):
        DatasetWriter(str(tmp_path), {})
    with pytest.raises(InvalidFrameError, match="set by the writer"):
        DatasetWriter(str(tmp_path), {"params": {}, "grid": {}})
    writer = DatasetWriter(str(tmp_path), {"params": {}}, grid=SMALL)
    for key in ("../x", "/abs", "a//b", ""):
        with pytest.raises(InvalidFrameError, match="shard key"):
            writer.write_shard(key, [_one()])
    with pytest.raises(InvalidFrameError, match="share a frame key"):
        writer.write_shard("s", [_one(), _one()])
