"""Checksums, missing shards and JSON-Schema validation of real writer output."""

from __future__ import annotations

import json

import jsonschema
import pyarrow.parquet as pq
import pytest

from nuplan_occ import schemas
from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import (
    MEMBERS, ChecksumError, DatasetFormatError, DatasetWriter, read_manifest, read_member, validate_dataset,
)
from nuplan_occ.storage.manifest import OPTIONAL_COLUMNS, base_schema
from nuplan_occ.synth.grid_frames import synthetic_log

SMALL = GridSpec(-4.0, 4.0, -4.0, 4.0, -1.0, 1.0, 0.25)


@pytest.fixture
def root(tmp_path):
    writer = DatasetWriter(str(tmp_path), {"params": {"seed": 0}}, grid=SMALL)
    records = synthetic_log(SMALL, "2021.06.07.12.54.00_veh-35_01843_02314", 7, [3, 3], members=list(MEMBERS),
                            failed=[4])
    writer.commit(writer.write_shard("2021.06/log7", records))
    return tmp_path


def test_real_output_validates_against_json_schemas(root):
    assert validate_dataset(str(root)) == []
    metadata = json.loads((root / "dataset.json").read_text())
    jsonschema.validate(metadata, schemas.load("dataset_metadata"))
    rows = read_manifest(str(root)).to_pylist()
    for row in rows:
        jsonschema.validate(row, schemas.load("manifest"))
    assert {row["status"] for row in rows} == {"ok", "failed"}
    assert metadata["grid"]["shape"] == [32, 32, 8] and metadata["members"]["semantics"]["level"] == 9


def test_manifest_schema_lists_every_column():
    names = base_schema(15).names
    assert schemas.load("manifest")["required"] == [n for n in names if n not in OPTIONAL_COLUMNS]
    assert names[-3:] == ["json_offset", "json_nbytes", "json_crc32"] and set(names[-3:]) == OPTIONAL_COLUMNS


def _fragment(root):
    """The first shard fragment of the fixture's manifest."""
    return sorted(root.glob("manifest/shards/**/*.parquet"))[0]


def test_schema_violation_is_reported(root):
    path = _fragment(root)
    table = pq.read_table(path)
    status = table["status"].to_pylist()
    status[0] = "maybe"
    pq.write_table(table.set_column(table.schema.get_field_index("status"), "status", [status]), path)
    problems = validate_dataset(str(root))
    assert any("status" in p and "'maybe'" in p for p in problems), problems


def test_corrupted_member_raises_checksum_error_naming_the_shard(root):
    shard = root / "shards" / "2021.06" / "log7.tar"
    row = read_manifest(str(root)).to_pylist()[1]
    data = bytearray(shard.read_bytes())
    data[row["semantics_offset"] + row["semantics_nbytes"] // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(ChecksumError, match=r"log7\.tar.*semantics") as err:
        read_member(str(root), row, "semantics")
    assert err.value.shard.endswith("shards/2021.06/log7.tar")
    with pytest.raises(ChecksumError):
        open_dataset(str(root))[1]
    other = open_dataset(str(root)).get(1, keys=("mask_lidar",))  # other members still read
    assert other["mask_lidar"].shape == SMALL.shape
    problems = validate_dataset(str(root))
    assert len(problems) == 1 and "checksum mismatch" in problems[0] and "sem.zst" in problems[0]


def test_missing_shard_and_bad_offsets_are_reported(root):
    path = _fragment(root)
    table = pq.read_table(path)
    offsets = table["mask_camera_offset"].to_pylist()
    offsets[0] += 512
    pq.write_table(table.set_column(table.schema.get_field_index("mask_camera_offset"), "mask_camera_offset",
                                    [offsets]), path)
    assert any("mask_camera" in p for p in validate_dataset(str(root)))
    (root / "shards" / "2021.06" / "log7.tar").unlink()
    problems = validate_dataset(str(root))
    assert problems == [f"{root}/shards/2021.06/log7.tar: shard missing (5 committed frames point to it)"]
    with pytest.raises(DatasetFormatError, match="shard named in the manifest is missing"):
        open_dataset(str(root))[0]


def test_unreadable_files_are_reported(tmp_path, root):
    assert "no dataset.json" in validate_dataset(str(tmp_path / "empty"))[0]
    meta = json.loads((root / "dataset.json").read_text())
    del meta["grid"]
    (root / "dataset.json").write_text(json.dumps(meta))
    assert validate_dataset(str(root)) == [f"{root}/dataset.json: <root>: 'grid' is a required property"]
    _fragment(root).write_bytes(b"not parquet")
    assert f"{_fragment(root)}: not a readable Parquet file" in validate_dataset(str(root))[0]
