"""On-disk dataset format: tar shards of per-frame zstd members + a Parquet manifest (the commit record),
published as one immutable fragment per scene and commit (`fragments.py`) and folded by `compact`.

Write with `DatasetWriter(root, metadata).write_shard(key, records)` then `.commit(rows)`; read with
`nuplan_occ.dataset.open_dataset(root)`, or low level with `read_manifest` / `read_member`.
"""

from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import (
    ChecksumError, DatasetFormatError, InvalidFrameError, MissingMemberError, StorageError,
)
from nuplan_occ.storage.manifest_reader import read_manifest
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.reader import ShardReader, read_member
from nuplan_occ.storage.records import FrameRecord, frame_key
from nuplan_occ.storage.validate import validate_dataset
from nuplan_occ.storage.writer import DatasetWriter, shard_exists

__all__ = [
    "MEMBERS", "ChecksumError", "DatasetFormatError", "InvalidFrameError", "MissingMemberError", "StorageError",
    "read_manifest", "read_metadata", "ShardReader", "read_member", "FrameRecord", "frame_key",
    "decode_throughput", "validate_dataset", "DatasetWriter", "shard_exists",
]
