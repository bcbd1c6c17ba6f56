"""The append-only manifest: per-shard fragments, newest commit wins, compaction, legacy datasets,
and the DuckDB / pyarrow one-liners of the README."""

from __future__ import annotations

import time

import fsspec
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import DatasetWriter, read_manifest, validate_dataset
from nuplan_occ.storage import fragments
from nuplan_occ.storage.compact import compact
from nuplan_occ.storage.manifest import rows_to_table, to_parquet_bytes
from nuplan_occ.storage.manifest_reader import ManifestIndex
from benchmarks.simulated_manifest import simulated_manifest
from nuplan_occ.synth.grid_frames import synthetic_log

SMALL = GridSpec(-4.0, 4.0, -4.0, 4.0, -1.0, 1.0, 0.25)


def _writer(root: str) -> DatasetWriter:
    return DatasetWriter(root, {"params": {}}, grid=SMALL)


def _speeds(root: str) -> list:
    return read_manifest(root)["ego_speed"].to_pylist()


def _commit_log(writer: DatasetWriter, log: str, log_id: int, scenes: list[int], speed: float) -> None:
    records = synthetic_log(SMALL, log, log_id, scenes, ego_speeds=[speed] * sum(scenes))
    writer.commit(writer.write_shard(log, records))


def test_rewritten_shard_supersedes_its_rows_even_with_a_clock_behind(monkeypatch):
    root = "memory://fragments-test/newest"
    writer = _writer(root)
    _commit_log(writer, "log-a", 0, [2, 3], speed=1.0)
    monkeypatch.setattr(time, "time_ns", lambda: 1_000)  # a machine whose clock is decades behind
    records = synthetic_log(SMALL, "log-a", 0, [2, 2], ego_speeds=[2.0] * 4)  # rebuilt with fewer frames
    writer.commit(writer.write_shard("log-a", records))
    table = read_manifest(root)
    assert table["ego_speed"].to_pylist() == [2.0] * 4  # old shard rows hidden, including the dropped frame
    assert table["frame_index"].to_pylist() == [0, 1, 2, 3]
    ids = pc.unique(table["commit_id"]).to_pylist()
    assert len(ids) == 1 and int(ids[0][:19]) > time.time_ns()
    assert len(fsspec.filesystem("memory").find("/fragments-test/newest/manifest")) == 2  # 1 shard x 2 commits
    assert len(open_dataset(root)) == 4 and validate_dataset(root) == []


def test_equal_rerun_commits_nothing_and_commit_reads_only_its_shards(tmp_path, monkeypatch):
    writer = _writer(str(tmp_path))
    _commit_log(writer, "log-a", 0, [3], speed=1.0)
    before = sorted(tmp_path.rglob("*.parquet"))
    _commit_log(writer, "log-a", 0, [3], speed=1.0)
    assert sorted(tmp_path.rglob("*.parquet")) == before
    listed = []
    original = fragments._commit_ids_in
    monkeypatch.setattr(fragments, "_commit_ids_in", lambda fs, folder: listed.append(folder) or original(fs, folder))
    _commit_log(writer, "log-b", 1, [3], speed=1.0)
    assert listed and all(f.endswith(("/shards/log-b", "/compacted")) for f in listed)  # never the whole manifest


def test_compaction_keeps_what_readers_see_and_is_safe_with_writers(tmp_path, monkeypatch):
    root = str(tmp_path)
    writer = _writer(root)
    for speed in (1.0, 2.0, 3.0):
        _commit_log(writer, "log-a", 0, [2, 2], speed)
    _commit_log(writer, "log-b", 1, [3], 5.0)
    seen = read_manifest(root)
    assert seen.num_rows == 7 and _speeds(root) == [3.0] * 4 + [5.0] * 3

    deleted = []
    monkeypatch.setattr(type(fsspec.filesystem("file")), "rm_file", lambda self, path: deleted.append(path))
    result = compact(root)  # "crashes" before deleting its inputs: output and inputs side by side
    assert result.rows_before == 15 and result.rows_after == 7 and len(deleted) == 4
    assert read_manifest(root).equals(seen)
    monkeypatch.undo()
    compact(root)
    assert [p.relative_to(tmp_path).parts[:2] for p in tmp_path.rglob("*.parquet")] == [("manifest", "compacted")]
    assert [p.name for p in (tmp_path / "manifest").iterdir()] == ["compacted"]  # no empty shard folders left
    assert read_manifest(root).equals(seen) and validate_dataset(root) == []

    monkeypatch.setattr(time, "time_ns", lambda: 1_000)  # a writer with a clock behind the compacted commits
    _commit_log(writer, "log-b", 1, [3], 6.0)
    assert _speeds(root) == [3.0] * 4 + [6.0] * 3
    compact(root)
    assert _speeds(root) == [3.0] * 4 + [6.0] * 3


def test_pre_fragment_manifest_stays_readable_and_is_superseded_per_shard(tmp_path):
    root = str(tmp_path)
    writer = _writer(root)
    rows = [r for log, lid in (("log-a", 0), ("log-b", 1))
            for r in writer.write_shard(log, synthetic_log(SMALL, log, lid, [3], ego_speeds=[1.0] * 3))]
    writer.commit([])  # dataset.json only
    legacy = rows_to_table(rows, writer._hist_len).drop_columns(["commit_id"])
    (tmp_path / "manifest.parquet").write_bytes(to_parquet_bytes(legacy))
    assert len(open_dataset(root)) == 6 and validate_dataset(root) == []
    assert read_manifest(root)["commit_id"].null_count == 6
    _commit_log(writer, "log-b", 1, [3], 4.0)
    assert _speeds(root) == [1.0] * 3 + [4.0] * 3
    compact(root)
    assert not (tmp_path / "manifest.parquet").exists() and _speeds(root) == [1.0] * 3 + [4.0] * 3


def test_scene_fragments_of_older_datasets_are_superseded_and_folded_away(tmp_path, monkeypatch):
    root = str(tmp_path)
    writer = _writer(root)
    records = synthetic_log(SMALL, "log-a", 0, [3], ego_speeds=[1.0] * 3)
    ahead = f"{time.time_ns() + 10**15:019d}-{0:016x}"  # written by a machine whose clock ran ahead
    old = rows_to_table(writer.write_shard("log-a", records), writer._hist_len)
    old = old.set_column(old.schema.get_field_index("commit_id"), "commit_id", pa.array([ahead] * 3))
    folder = tmp_path / "manifest" / "scenes" / "log-a" / records[0].scene_token
    folder.mkdir(parents=True)
    pq.write_table(old, folder / f"{ahead}.parquet")
    assert _speeds(root) == [1.0] * 3
    _commit_log(writer, "log-a", 0, [3], 2.0)  # the same shard rebuilt
    assert _speeds(root) == [2.0] * 3
    compact(root)
    assert [p.name for p in (tmp_path / "manifest").iterdir()] == ["compacted"] and _speeds(root) == [2.0] * 3


def _unknown_identity(records: list) -> list:
    """The records as an imported release without its logs gives them: only the token is known."""
    for r in records:
        r.log = r.scene_token = r.scene_name = r.log_id = r.frame_index = r.timestamp_us = r.ego_to_global = None
    return records


def test_shard_is_the_unit_so_chunks_of_a_scene_and_of_unknown_scenes_stay_visible(tmp_path):
    root = str(tmp_path)
    writer = _writer(root)
    scene = synthetic_log(SMALL, "log-a", 0, [4])
    writer.commit(writer.write_shard("log-a/part-0", scene[:2]))  # one scene over two commits
    writer.commit(writer.write_shard("log-a/part-1", scene[2:]))
    unknown = _unknown_identity(synthetic_log(SMALL, "log-u", 1, [3]))
    writer.commit(writer.write_shard("release/part-0", unknown[:2]))  # null scene_token, two commits
    writer.commit(writer.write_shard("release/part-1", unknown[2:]))
    index = ManifestIndex(root)
    assert sorted(index.column("token").to_pylist()) == sorted(r.token for r in scene + unknown)
    codes = index.scene_codes
    known = index.column("scene_token").is_valid().to_numpy(zero_copy_only=False)
    assert len(set(codes[known])) == 1 and len(set(codes[~known])) == 3 and not set(codes[known]) & set(codes[~known])
    writer.commit(writer.write_shard("log-a/part-0", scene[:1]))  # rewritten with fewer frames
    assert sorted(read_manifest(root)["token"].to_pylist()) == sorted(r.token for r in scene[:1] + scene[2:] + unknown)
    assert validate_dataset(root) == []


def test_readme_queries_duckdb_and_pyarrow_dataset(tmp_path):
    duckdb = pytest.importorskip("duckdb")
    root = str(tmp_path)
    writer = _writer(root)
    for speed in (1.0, 2.0):
        _commit_log(writer, "log-a", 0, [2, 2], speed)
    _commit_log(writer, "log-b", 1, [3], 5.0)
    expected = read_manifest(root)
    # the README's line, verbatim but for the root
    query = (f"SELECT * FROM read_parquet('{root}/manifest/**/*.parquet', union_by_name = true) "
             "QUALIFY commit_id = max(commit_id) OVER (PARTITION BY shard) "
             "AND row_number() OVER (PARTITION BY shard, token ORDER BY commit_id DESC) = 1 "
             "ORDER BY log_id, timestamp_us, frame_index, token")
    got = duckdb.sql(query).arrow()
    got = got.read_all() if hasattr(got, "read_all") else got
    assert got["token"].to_pylist() == expected["token"].to_pylist()
    assert got["ego_speed"].to_pylist() == expected["ego_speed"].to_pylist()
    every_commit = pads.dataset(f"{root}/manifest", format="parquet").to_table()
    assert every_commit.num_rows == 11 and set(every_commit["commit_id"].to_pylist()) >= set(expected["commit_id"].to_pylist())


def test_reader_opens_with_index_columns_only_and_finds_frames(tmp_path, monkeypatch):
    table = simulated_manifest(60, 50)
    (tmp_path / "manifest" / "compacted").mkdir(parents=True)
    pq.write_table(table, tmp_path / "manifest" / "compacted" / "a.parquet", row_group_size=1000)
    _writer(str(tmp_path)).commit([])
    read_columns = []
    original = pq.ParquetFile.read
    monkeypatch.setattr(pq.ParquetFile, "read", lambda self, columns=None, **kw: read_columns.extend(columns)
                        or original(self, columns, **kw))
    ds = open_dataset(str(tmp_path))
    assert set(read_columns) == {"shard", "scene_token", "commit_id", "log_id", "timestamp_us", "frame_index", "status"}
    monkeypatch.undo()
    ok = table.filter(pc.equal(table["status"], "ok"))
    assert len(ds) == ok.num_rows == 2940
    for i in (0, 1234, len(ds) - 1):
        token = ok["token"][i].as_py()
        assert ds.index_of_token(token) == i
        identity = ds.identity(i)
        assert identity["token"] == token and identity["frame_index"] == ok["frame_index"][i].as_py()
        np.testing.assert_array_equal(identity["ego_to_global"].reshape(-1), ok["ego_to_global"][i].as_py())
    with pytest.raises(KeyError):
        ds.index_of_token("f" * 32)
    np.testing.assert_array_equal(ds.column("ego_speed").to_numpy(), ok["ego_speed"].to_numpy())
    assert ds.scene_codes.max() + 1 == 60
    assert pa.types.is_integer(pa.array(ds.frame_index).type)
