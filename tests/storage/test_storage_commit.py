"""Commit semantics: deterministic bytes, manifest as commit record, crash safety, row replacement."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import read_metadata, DatasetFormatError, DatasetWriter, read_manifest, shard_exists, validate_dataset
from nuplan_occ.storage.digest import content_digests
from nuplan_occ.synth.grid_frames import synthetic_log

SMALL = GridSpec(-4.0, 4.0, -4.0, 4.0, -1.0, 1.0, 0.25)
MEMBERS_USED = ["semantics", "mask_lidar", "flow"]


def _logs() -> dict[str, list]:
    return {
        "log-b": synthetic_log(SMALL, "log-b", 1, [3, 2], members=MEMBERS_USED, failed=[1]),
        "log-a": synthetic_log(SMALL, "log-a", 0, [4], members=MEMBERS_USED),
    }


def _writer(root: Path, params: dict | None = None) -> DatasetWriter:
    return DatasetWriter(str(root), {"params": params or {"voxel": 0.25}}, grid=SMALL)


def _build(root: Path, batches: list[list[str]]) -> None:
    """Write every log's shard, committing the logs in the given batches."""
    writer, logs = _writer(root), _logs()
    for batch in batches:
        writer.commit([row for log in batch for row in writer.write_shard(log, logs[log])])


def _files(root: Path) -> dict[str, str]:
    return content_digests(str(root))


def test_outputs_are_byte_identical_across_runs_and_commit_batching(tmp_path):
    _build(tmp_path / "one", [["log-a", "log-b"]])
    _build(tmp_path / "two", [["log-a", "log-b"]])
    _build(tmp_path / "batched", [["log-b"], ["log-a"]])
    one = _files(tmp_path / "one")
    assert set(one) == {"dataset.json", "manifest", "shards/log-a.tar", "shards/log-b.tar"}
    assert one == _files(tmp_path / "two") == _files(tmp_path / "batched")
    fragments = sorted(p.relative_to(tmp_path / "batched").parts[:3] for p in (tmp_path / "batched").rglob("*.parquet"))
    assert fragments == [("manifest", "shards", "log-a"), ("manifest", "shards", "log-b")]  # one per shard


def test_manifest_sorted_and_failed_rows_kept(tmp_path):
    _build(tmp_path, [["log-b", "log-a"]])
    table = read_manifest(str(tmp_path))
    assert table["log"].to_pylist() == ["log-a"] * 4 + ["log-b"] * 5
    assert table["frame_index"].to_pylist() == [0, 1, 2, 3, 0, 1, 2, 3, 4]
    failed = table.filter(table["status"].to_numpy(zero_copy_only=False) == "failed").to_pylist()
    assert len(failed) == 1 and failed[0]["failure_reason"] == "synthetic failure"
    assert failed[0]["semantics_offset"] is None and failed[0]["class_hist"] is None
    assert len(open_dataset(str(tmp_path))) == 8


def test_uncommitted_shard_is_not_part_of_the_dataset(tmp_path):
    writer, logs = _writer(tmp_path), _logs()
    writer.commit(writer.write_shard("log-a", logs["log-a"]))
    writer.write_shard("log-b", logs["log-b"])  # crash here: shard published, commit never ran
    assert shard_exists(str(tmp_path), "log-b") and not shard_exists(str(tmp_path), "log-c")
    assert set(read_manifest(str(tmp_path))["log"].to_pylist()) == {"log-a"}
    assert len(open_dataset(str(tmp_path))) == 4
    assert validate_dataset(str(tmp_path)) == []


def test_crash_during_publish_leaves_temp_only_and_rerun_is_identical(tmp_path, monkeypatch):
    _build(tmp_path / "clean", [["log-a", "log-b"]])
    root = tmp_path / "crashed"
    writer, logs = _writer(root), _logs()
    writer.commit(writer.write_shard("log-a", logs["log-a"]))

    def crash(src, dst):
        raise OSError("simulated crash before rename")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="simulated crash"):
        writer.write_shard("log-b", logs["log-b"])
    monkeypatch.undo()
    assert [p.name for p in (root / "shards").iterdir()] == ["log-a.tar"]  # the failed write removed its temp
    (root / "shards" / ".log-b.tar.tmp-1-deadbeef").write_bytes(b"half a tar")  # a killed writer's temp file
    fragment_dir = root / "manifest" / "shards" / "log-a"
    (fragment_dir / ".1796162835093246242-11ecdfd64da418a0.parquet.tmp-1-deadbeef").write_bytes(b"half a parquet file")
    assert len(open_dataset(str(root))) == 4
    assert validate_dataset(str(root)) == []

    _build(root, [["log-a", "log-b"]])  # rerun
    assert _files(root) == _files(tmp_path / "clean")


def test_commit_replaces_rows_of_equal_log_and_token(tmp_path):
    writer, logs = _writer(tmp_path), _logs()
    writer.commit(writer.write_shard("log-a", logs["log-a"]))
    for record in logs["log-a"]:
        record.columns["ego_speed"] = 0.5
        record.columns["qa_ok"] = True
    writer.commit(writer.write_shard("log-a", logs["log-a"]))
    table = read_manifest(str(tmp_path))
    assert table.num_rows == 4
    assert table["ego_speed"].to_pylist() == [0.5] * 4 and table["qa_ok"].to_pylist() == [True] * 4


def test_commit_publishes_the_latest_metadata_and_refuses_missing_shards(tmp_path):
    writer, logs = _writer(tmp_path), _logs()
    rows = writer.write_shard("log-a", logs["log-a"])
    writer.commit(rows)
    _writer(tmp_path, {"voxel": 0.5}).commit(rows)
    assert read_metadata(str(tmp_path))["params"] == {"voxel": 0.5}
    (tmp_path / "shards" / "log-a.tar").unlink()
    with pytest.raises(DatasetFormatError, match="shard of committed rows is missing"):
        writer.commit(rows)


def test_shard_of_only_failed_frames(tmp_path):
    writer = _writer(tmp_path)
    records = synthetic_log(SMALL, "log-c", 2, [3], failed=[0, 1, 2])
    writer.commit(writer.write_shard("log-c/scene0", records))
    assert read_manifest(str(tmp_path)).num_rows == 3
    assert len(open_dataset(str(tmp_path))) == 0
    assert validate_dataset(str(tmp_path)) == []
