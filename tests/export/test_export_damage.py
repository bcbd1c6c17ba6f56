"""Export skips a frame whose members cannot be read, names it and the member, writes the rest and ends
non-zero."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from nuplan_occ.export.formats import export_dataset, invert_occ3d
from nuplan_occ.storage import read_manifest
from nuplan_occ.storage.errors import DamagedManifestWarning, DatasetFormatError
from tools_world import SMALL, small_scene, token_of, write_dataset

N_FRAMES = 5


@pytest.fixture
def source(tmp_path):
    """Five frames with semantics and a lidar mask, one shard; returns (root, frames, manifest rows)."""
    rng = np.random.default_rng(5)
    frames = [{"semantics": small_scene(i), "mask_lidar": rng.random(SMALL.shape) < 0.5} for i in range(N_FRAMES)]
    root = tmp_path / "src"
    write_dataset(root, frames)
    return root, frames, read_manifest(str(root)).to_pylist()


def _flip(root, row: dict, member: str) -> None:
    shard = root / "shards" / f"{row['shard']}.tar"
    data = bytearray(shard.read_bytes())
    data[row[f"{member}_offset"] + row[f"{member}_nbytes"] // 2] ^= 0x10
    shard.write_bytes(bytes(data))


def test_bad_frames_are_skipped_and_named_the_rest_exported(source, tmp_path):
    root, frames, rows = source
    _flip(root, rows[1], "semantics")
    _flip(root, rows[3], "mask_lidar")
    summary = export_dataset(str(root), tmp_path / "out", "occ3d")
    assert summary["frames"] == N_FRAMES - 2
    assert [(s["frame"], s["token"], s["member"]) for s in summary["skipped"]] == [
        (rows[1]["key"], token_of(1), "semantics"), (rows[3]["key"], token_of(3), "mask_lidar")]
    assert all("checksum" in s["problem"] or "crc32" in s["problem"] for s in summary["skipped"])
    for i, arrays in enumerate(frames):
        path = tmp_path / "out" / "gts" / f"scene-{'ab' * 8}" / token_of(i) / "labels.npz"
        assert path.exists() == (i not in (1, 3))
        if path.exists():
            with np.load(path) as npz:
                assert np.array_equal(invert_occ3d(npz["semantics"]), arrays["semantics"])
                assert np.array_equal(npz["mask_lidar"].astype(bool), arrays["mask_lidar"])
    listed = json.loads((tmp_path / "out" / "export.json").read_text())
    assert [f["token"] for f in listed["frame_list"]] == [token_of(i) for i in (0, 2, 4)]
    assert len(listed["skipped"]) == 2


def test_truncated_shard_skips_only_the_frames_past_its_end(source, tmp_path):
    root, frames, rows = source
    shard = root / "shards" / f"{rows[0]['shard']}.tar"
    shard.write_bytes(shard.read_bytes()[: rows[-1]["semantics_offset"] + 10])
    summary = export_dataset(str(root), tmp_path / "out", "uniscene")
    assert summary["frames"] == N_FRAMES - 1
    [skipped] = summary["skipped"]
    assert (skipped["frame"], skipped["member"]) == (rows[-1]["key"], "semantics") and "truncated" in skipped["problem"]


def test_cli_reports_each_skipped_frame_in_one_line_and_exits_non_zero(source, tmp_path, capsys):
    from nuplan_occ.cli import app

    root, _, rows = source
    _flip(root, rows[2], "semantics")
    with pytest.raises(SystemExit) as done:
        app(["export", str(root), str(tmp_path / "out"), "--format", "uniscene", "--frame", "ego"], prog_name="nuplan-occ")
    err = capsys.readouterr().err.splitlines()
    assert done.value.code == 1
    assert err[0].startswith(f"skipped frame {rows[2]['key']}, member semantics: ") and "crc32" in err[0]
    assert err[1:] == ["1 frame(s) skipped, 0 unreadable manifest file(s): the export is incomplete"]
    assert len(list((tmp_path / "out").rglob("*.npy"))) == N_FRAMES - 1


def test_unreadable_manifest_is_skipped_or_refused_with_strict(source, tmp_path):
    root, _, _ = source
    target = root / "manifest" / "shards" / "other-scene" / "1796000000000000000-0123456789abcdef.parquet"
    target.parent.mkdir(parents=True)
    target.write_bytes(b"PAR1 a fragment cut short")  # another shard's fragment, damaged
    with pytest.raises(DatasetFormatError, match="not a readable Parquet file"):
        export_dataset(str(root), tmp_path / "strict", "uniscene", strict=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DamagedManifestWarning)
        summary = export_dataset(str(root), tmp_path / "out", "uniscene")
    assert summary["frames"] == N_FRAMES and summary["skipped"] == []
    assert len(summary["damaged_manifest"]) == 1 and str(target) in summary["damaged_manifest"][0]
