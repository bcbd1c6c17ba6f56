"""The reader at dataset scale on simulated manifest rows (no shards): 200 k rows in a compacted file plus
fragments that rewrite, add and interleave shards. Checked against the rows themselves: which rows are
visible and in what order, frames found by index and by token, and the clip index of `OccupancyDataset`
against a brute-force count. Speed is the manifest bench's business."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.storage import DatasetWriter, token_index
from nuplan_occ.storage.fragments import shard_dir
from nuplan_occ.storage.manifest import SORT_KEYS
from benchmarks.simulated_manifest import simulated_manifest
from nuplan_occ.torch import OccupancyDataset

SCENES, FRAMES = 1_000, 200
REWRITTEN = range(0, SCENES, 97)  # shards rewritten by a newer commit with fewer, faster frames
NEWER = 1_797_000_000_000_000_000


def _stamped(rows: pa.Table, commit: str) -> pa.Table:
    return rows.set_column(rows.schema.get_field_index("commit_id"), "commit_id", pa.array([commit] * rows.num_rows))


def _fragment(root: Path, rows: pa.Table, commit: str) -> None:
    folder = Path(shard_dir(str(root), rows["shard"][0].as_py()))
    folder.mkdir(parents=True, exist_ok=True)
    pq.write_table(_stamped(rows, commit), folder / f"{commit}.parquet")


@pytest.fixture(scope="module")
def scaled(tmp_path_factory):
    """(root, the visible rows in manifest order) of a 200 k-row compacted manifest with fragments."""
    root = tmp_path_factory.mktemp("scale")
    table = simulated_manifest(SCENES, FRAMES)
    (root / "manifest" / "compacted").mkdir(parents=True)
    pq.write_table(table, root / "manifest" / "compacted" / f"{table['commit_id'][-1].as_py()}.parquet",
                   row_group_size=16384)
    visible = [table.slice(s * FRAMES, FRAMES) for s in range(SCENES) if s not in REWRITTEN]
    for k, s in enumerate(REWRITTEN):
        rows = table.slice(s * FRAMES, FRAMES // 2)
        rows = rows.set_column(rows.schema.get_field_index("ego_speed"), "ego_speed", pa.array([9.0] * rows.num_rows))
        _fragment(root, rows, f"{NEWER + k:019d}-{k:016x}")
        visible.append(rows)
    extra = simulated_manifest(3, FRAMES, seed=1)  # new shards whose log ids sort before every other
    for s in range(3):
        rows = extra.slice(s * FRAMES, FRAMES)
        rows = rows.set_column(rows.schema.get_field_index("log_id"), "log_id", pa.array([-1 - s] * FRAMES, pa.int64()))
        for name in ("log", "shard", "key"):
            rows = rows.set_column(rows.schema.get_field_index(name), name, pc.binary_join_element_wise("new", rows[name], "-"))
        _fragment(root, rows, f"{NEWER + 500 + s:019d}-{s:016x}")
        visible.append(rows)
    DatasetWriter(str(root), {"params": {}}).commit([])
    expected = pa.concat_tables([_stamped(t, "x") for t in visible]).sort_by([(k, "ascending") for k in SORT_KEYS])
    return str(root), expected


def test_open_finds_the_visible_ok_frames_by_index_and_token(scaled, monkeypatch):
    root, expected = scaled
    read = []
    original = pq.ParquetFile.read
    monkeypatch.setattr(pq.ParquetFile, "read", lambda self, columns=None, **kw: read.extend(columns) or original(self, columns, **kw))
    ds = open_dataset(root)
    assert set(read) == {"shard", "scene_token", "commit_id", "status", "log_id", "timestamp_us", "frame_index"}
    monkeypatch.undo()
    ok = expected.filter(pc.equal(expected["status"], "ok"))
    assert len(ds) == ok.num_rows
    np.testing.assert_array_equal(ds.frame_index, ok["frame_index"].to_numpy())
    scenes = ok["scene_token"].to_pylist()
    assert len(set(zip(scenes, ds.scene_codes.tolist()))) == len(set(scenes)) == len(set(ds.scene_codes.tolist()))
    assert ds.scene_codes.max() + 1 == len(set(scenes))
    tokens = ok["token"].to_pylist()
    for i in np.random.default_rng(0).integers(0, len(ds), 40).tolist() + [0, len(ds) - 1]:
        assert ds.identity(i)["token"] == tokens[i]
        assert ds.index_of_token(tokens[i]) == i
    failed = expected.filter(pc.equal(expected["status"], "failed"))["token"][0].as_py()
    hidden = simulated_manifest(SCENES, FRAMES)["token"][REWRITTEN[1] * FRAMES + FRAMES - 2].as_py()  # ok, superseded
    for token in (failed, hidden, "f" * 32, ""):
        with pytest.raises(KeyError):
            ds.index_of_token(token)


def test_token_lookup_checks_candidates_when_hashes_collide(scaled, monkeypatch):
    root, expected = scaled
    monkeypatch.setattr(token_index, "string_hashes", lambda values: np.zeros(len(values), dtype=np.uint64))
    ds = open_dataset(root)
    tokens = expected.filter(pc.equal(expected["status"], "ok"))["token"].to_pylist()
    assert ds.index_of_token(tokens[12_345]) == 12_345
    with pytest.raises(KeyError):
        ds.index_of_token("not-a-token")


def test_string_hashes_differ_for_strings_of_any_length():
    values = ["", "a", "a\0", "abcdefgh", "abcdefghi", "x" * 16, "x" * 17, "é", None]
    hashes = token_index.string_hashes(pa.array(values))
    assert len(set(hashes[:-1].tolist())) == len(values) - 1 and hashes[-1] == hashes[0]
    assert token_index.string_hashes(pa.array(values[3:5]))[1] == hashes[4]  # independent of the other rows


def _brute_force_clips(ok: pa.Table, clip_len: int, stride: int, theta_e: float) -> list[list[str]]:
    """Token lists of the spatial clips, by walking every scene's frames in time order."""
    by_scene = defaultdict(list)
    for row in ok.select(["scene_token", "output_index", "ego_speed", "token"]).to_pylist():
        by_scene[row["scene_token"]].append(row)
    clips = []
    for scene in dict.fromkeys(ok["scene_token"].to_pylist()):
        frames = sorted(by_scene[scene], key=lambda r: r["output_index"])
        runs, run = [], [frames[0]]
        for previous, frame in zip(frames, frames[1:]):
            if frame["output_index"] == previous["output_index"] + 1:
                run.append(frame)
            else:
                runs.append(run)
                run = [frame]
        runs.append(run)
        for run in runs:
            for start in range(0, len(run) - clip_len + 1, stride):
                clip = run[start:start + clip_len]
                if all(f["ego_speed"] > theta_e for f in clip):
                    clips.append([f["token"] for f in clip])
    return clips


def test_clip_index_equals_a_brute_force_walk(scaled):
    root, expected = scaled
    ok = expected.filter(pc.equal(expected["status"], "ok"))
    occ = OccupancyDataset(root, clip_len=8, stride=4, subset="spatial")
    reference = _brute_force_clips(ok, 8, 4, theta_e=1.0)
    assert len(occ) == len(reference) > 0
    tokens = np.array(ok["token"].to_pylist())
    for i in np.random.default_rng(1).integers(0, len(occ), 30).tolist() + [0, len(occ) - 1]:
        assert tokens[occ.frame_indices(i)].tolist() == reference[i]
