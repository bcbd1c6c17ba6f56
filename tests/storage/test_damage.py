"""Damaged datasets never take a reader down: unreadable manifest fragments are skipped and described
(or refused with strict), compaction never folds them away, validate checks the json member, and a
failed write (a full disk) is one error naming the path with everything published before kept."""

from __future__ import annotations

import errno
import os
import warnings
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.stats import dataset_stats
from nuplan_occ.storage import DatasetFormatError, DatasetWriter, MEMBERS, read_manifest, validate_dataset
from nuplan_occ.storage import fsio
from nuplan_occ.storage.compact import compact
from nuplan_occ.storage.errors import DamagedManifestWarning, StorageWriteError
from nuplan_occ.storage.manifest import OPTIONAL_COLUMNS
from nuplan_occ.synth.grid_frames import synthetic_arrays, synthetic_log

SMALL = GridSpec(-4.0, 4.0, -4.0, 4.0, -1.0, 1.0, 0.25)
DAMAGE = {
    "zero bytes": lambda data: b"",
    "truncated": lambda data: data[: len(data) // 2],
    "garbage": lambda data: bytes(np.random.default_rng(0).integers(0, 256, len(data), dtype=np.uint8)),
}


def _commit(root: Path, log: str, log_id: int, speed: float, members=("semantics",)) -> list[str]:
    """Commit one shard named `log` (scenes of 2 and 2 frames, ego_speed `speed`); the fragment paths."""
    writer = DatasetWriter(str(root), {"params": {}}, grid=SMALL)
    records = synthetic_log(SMALL, log, log_id, [2, 2], ego_speeds=[speed] * 4, members=list(members))
    return writer.commit(writer.write_shard(log, records))


def _damage(path: str | Path, kind: str) -> None:
    path = Path(path)
    path.write_bytes(DAMAGE[kind](path.read_bytes()))


def _open_warned(root: Path, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = open_dataset(str(root), **kwargs)
    return ds, [str(w.message) for w in caught if issubclass(w.category, DamagedManifestWarning)]


@pytest.mark.parametrize("kind", sorted(DAMAGE))
def test_unreadable_fragment_is_skipped_and_its_frames_listed_as_unreadable(tmp_path, kind):
    _commit(tmp_path, "log-a", 0, 1.0, members=MEMBERS)
    [bad] = _commit(tmp_path, "log-b", 1, 2.0)
    _damage(bad, kind)
    ds, warned = _open_warned(tmp_path)
    assert len(ds) == 4 and ds.column("log").to_pylist() == ["log-a"] * 4  # the intact shard, whole
    for i in range(4):
        assert np.array_equal(ds[i]["instance"], synthetic_arrays(SMALL, i, ["instance"])["instance"])
    [damaged] = ds.damaged
    assert (damaged.path, damaged.shard_folder, damaged.outcome) == (bad, "log-b", "unreadable")
    assert warned == [damaged.describe()] and "\n" not in warned[0]
    assert warned[0].startswith(f"{bad}: unreadable manifest file skipped (") and "unreadable until" in warned[0]

    with pytest.warns(DamagedManifestWarning):
        stats = dataset_stats(str(tmp_path))  # figures of the readable rows; the lost shard listed
    assert stats["frames"]["total"] == 4 and stats["frames"]["logs"] == 1
    assert [(d["path"], d["outcome"]) for d in stats["damaged"]] == [(bad, "unreadable")]
    with pytest.raises(DatasetFormatError, match="not a readable Parquet file"):
        open_dataset(str(tmp_path), strict=True)
    with pytest.raises(DatasetFormatError, match=bad):
        dataset_stats(str(tmp_path), strict=True)


def test_rows_fall_back_to_the_previous_commit_or_newer_one_is_read(tmp_path):
    [first] = _commit(tmp_path, "log-a", 0, 1.0)
    [second] = _commit(tmp_path, "log-a", 0, 2.0)
    _damage(second, "truncated")
    ds, warned = _open_warned(tmp_path)
    assert ds.column("ego_speed").to_pylist() == [1.0] * 4  # the earlier commit's rows
    first_commit = Path(first).stem
    assert ds.damaged[0].outcome == "fallback" and ds.damaged[0].fallback_commit == first_commit
    assert f"earlier commit {first_commit}" in warned[0]

    Path(second).unlink()
    [third] = _commit(tmp_path, "log-a", 0, 3.0)
    _damage(first, "garbage")  # an older commit damaged: nothing is missing
    ds, _ = _open_warned(tmp_path)
    assert ds.column("ego_speed").to_pylist() == [3.0] * 4
    assert [d.outcome for d in ds.damaged] == ["superseded"] and Path(third).exists()


def test_rebuilding_a_shard_whose_newest_fragment_is_damaged_publishes_it_again(tmp_path):
    [bad] = _commit(tmp_path, "log-a", 0, 1.0)
    _damage(bad, "zero bytes")
    [again] = _commit(tmp_path, "log-a", 0, 1.0)  # equal rows, but the stored ones cannot be read
    assert again != bad and Path(again).stem > Path(bad).stem
    ds, _ = _open_warned(tmp_path)
    assert len(ds) == 4 and [d.outcome for d in ds.damaged] == ["superseded"]


def test_compact_never_folds_a_damaged_fragment_away(tmp_path):
    _commit(tmp_path, "log-a", 0, 1.0)
    [older] = _commit(tmp_path, "log-b", 1, 2.0)
    [bad] = _commit(tmp_path, "log-b", 1, 5.0)
    _commit(tmp_path, "log-c", 2, 3.0)
    damaged_bytes = DAMAGE["truncated"](Path(bad).read_bytes())
    Path(bad).write_bytes(damaged_bytes)
    with pytest.warns(DamagedManifestWarning):
        before = read_manifest(str(tmp_path))
    files_before = sorted(tmp_path.rglob("*.parquet"))

    with pytest.raises(DatasetFormatError, match="not a readable Parquet file"):
        compact(str(tmp_path), strict=True)
    assert sorted(tmp_path.rglob("*.parquet")) == files_before  # strict: nothing written or deleted

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DamagedManifestWarning)
        result = compact(str(tmp_path))
        after = read_manifest(str(tmp_path))
    assert [d.path for d in result.damaged] == [bad] and result.files_before == 3
    assert Path(bad).read_bytes() == damaged_bytes and not Path(older).exists()  # kept as it was
    assert sorted(tmp_path.rglob("*.parquet")) == sorted([Path(result.output), Path(bad)])
    assert after.equals(before)  # log-b still reads its earlier commit
    assert after["ego_speed"].to_pylist() == [1.0] * 4 + [2.0] * 4 + [3.0] * 4


def test_validate_reports_a_damaged_fragment_and_still_checks_the_rest(tmp_path):
    _commit(tmp_path, "log-a", 0, 1.0)
    [bad] = _commit(tmp_path, "log-b", 1, 2.0)
    row = read_manifest(str(tmp_path)).to_pylist()[2]
    _damage(bad, "garbage")
    shard = tmp_path / "shards" / "log-a.tar"
    data = bytearray(shard.read_bytes())
    data[row["semantics_offset"] + 3] ^= 0x01
    shard.write_bytes(bytes(data))
    with warnings.catch_warnings():
        warnings.simplefilter("error", DamagedManifestWarning)  # validate reports, it does not warn
        problems = validate_dataset(str(tmp_path))
    assert len(problems) == 2
    assert problems[0].startswith(f"{bad}: unreadable manifest file skipped")
    assert f"{row['key']}.sem.zst" in problems[1] and "checksum mismatch" in problems[1]


def _flip_in_json(root: Path, key: str, old: bytes, new: bytes) -> None:
    """Replace `old` by `new` (same length) inside frame `key`'s json member of shard log-a."""
    shard = root / "shards" / "log-a.tar"
    data = shard.read_bytes()
    start = data.index(f"{key}.json".encode())
    start = data.index(b"{", start + 512)
    at = data.index(old, start)
    shard.write_bytes(data[:at] + new + data[at + len(old):])


def test_validate_detects_a_flipped_byte_in_the_json_member(tmp_path):
    _commit(tmp_path, "log-a", 0, 1.0)
    row = read_manifest(str(tmp_path)).to_pylist()[1]
    assert row["json_crc32"] is not None and row["json_nbytes"] > 0
    assert validate_dataset(str(tmp_path)) == []
    _flip_in_json(tmp_path, row["key"], b'"frame_index": 1', b'"frame_index": 7')
    problems = validate_dataset(str(tmp_path))
    assert len(problems) == 1 and f"{row['key']}.json: crc32" in problems[0] and "checksum mismatch" in problems[0]
    assert len(open_dataset(str(tmp_path))) == 4  # readers do not use the json member


def test_validate_checks_json_members_of_manifests_written_before_their_checksum(tmp_path):
    [fragment] = _commit(tmp_path, "log-a", 0, 1.0)
    table = pq.read_table(fragment)
    pq.write_table(table.drop_columns(sorted(OPTIONAL_COLUMNS)), fragment)  # an older writer's manifest
    assert validate_dataset(str(tmp_path)) == []
    key = read_manifest(str(tmp_path))["key"].to_pylist()[2]
    _flip_in_json(tmp_path, key, b'"frame_index": 2', b'"frame_index": 3')
    problems = validate_dataset(str(tmp_path))
    assert problems == [f"{tmp_path}/shards/log-a.tar: {key}.json: differs from its manifest row in frame_index"]
    _flip_in_json(tmp_path, key, b'"frame_index": 3', b'"frame_index"\x00 3')
    [problem] = validate_dataset(str(tmp_path))
    assert f"{key}.json: not valid JSON" in problem


def _disk_full_after(monkeypatch, allowed: int) -> None:
    """Local publishing fails with ENOSPC once `allowed` more files have been written."""
    create = fsio._create
    left = [allowed]

    class FullFile:
        def __init__(self, handle):
            self._handle = handle

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._handle.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def failing_create(path: str, attempts: int = 3):
        handle = create(path, attempts)
        left[0] -= 1
        return handle if left[0] >= 0 else FullFile(handle)

    monkeypatch.setattr(fsio, "_create", failing_create)


@pytest.mark.parametrize("allowed, failing", [(0, "shards/log-b.tar"), (2, "manifest/shards/log-b/")])
def test_full_disk_names_the_file_and_keeps_what_was_published(tmp_path, monkeypatch, allowed, failing):
    _commit(tmp_path, "log-a", 0, 1.0)
    before = read_manifest(str(tmp_path))
    _disk_full_after(monkeypatch, allowed)  # the shard, dataset.json, then the fragment
    with pytest.raises(StorageWriteError) as err:
        _commit(tmp_path, "log-b", 1, 2.0)
    monkeypatch.undo()
    assert err.value.errno == errno.ENOSPC and err.value.filename.startswith(f"{tmp_path}/{failing}")
    assert str(err.value).startswith(f"{err.value.filename}: no space left on device")
    assert not [p for p in tmp_path.rglob("*") if fsio.TEMP_MARKER in p.name]  # no temp file left behind
    assert read_manifest(str(tmp_path)).equals(before) and validate_dataset(str(tmp_path)) == []


def test_cli_warns_in_one_line_and_strict_refuses(tmp_path, capsys):
    from nuplan_occ.cli import app

    _commit(tmp_path, "log-a", 0, 1.0)
    [bad] = _commit(tmp_path, "log-b", 1, 2.0)
    _damage(bad, "zero bytes")

    def run(*args: str) -> tuple[int, str, str]:
        with pytest.raises(SystemExit) as done:
            app([*args, str(tmp_path)], prog_name="nuplan-occ")
        out = capsys.readouterr()
        return done.value.code, out.out, out.err

    code, out, err = run("stats")
    assert code == 0 and "Traceback" not in err
    assert err.splitlines() == [f"nuplan-occ: warning: {bad}: unreadable manifest file skipped (not a readable "
                                "Parquet file (Parquet file size is 0 bytes)); no earlier commit of its shard: the "
                                "shard's frames are unreadable until it is rebuilt"]
    assert "unreadable manifest files" in out and "its frames are missing" in out
    code, out, err = run("stats", "--strict")
    assert code == 1 and err.splitlines() == [
        f"nuplan-occ: error: {bad}: not a readable Parquet file (Parquet file size is 0 bytes)"]
    code, out, err = run("compact")
    assert code == 1 and Path(bad).exists() and err.splitlines()[-1] == (
        "1 unreadable manifest file(s) left in place, not folded")
