"""Manifest rows as Arrow tables: one row per frame, the commit record of the dataset (files and
commits: `fragments.py`; reading: `manifest_reader.py`).

Column order is fixed: the base columns below, then `<member>_offset`, `<member>_nbytes`,
`<member>_crc32` for every member of `MEMBERS` (null when the frame lacks the member) and for the
frame's json member (`FRAME_JSON`), then the extra columns of the records (`FrameRecord.columns`)
sorted by name. Rows are sorted by
(log_id, timestamp_us, frame_index, token) and unique in (log, token). Offsets are byte offsets of a
member's data inside `<root>/shards/<shard>.tar`; crc32 is `zlib.crc32` of the stored (compressed)
bytes. `class_hist[i]` counts the voxels of label id i (length = largest label id + 1).
`ego_to_global` is T_global_from_ego flattened row-major (16 float64). `commit_id` names the commit
that published the row (null in datasets written before commit ids; see `fragments.py`).
"""

from __future__ import annotations

import io

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import InvalidFrameError

ROW_GROUP_SIZE = 131072
SORT_KEYS = ("log_id", "timestamp_us", "frame_index", "token")

MEMBER_FIELDS = ("offset", "nbytes", "crc32")
FRAME_JSON = "json"
"""The `<key>.json` member of every ok frame: its identity, member suffixes and extra columns, for
WebDataset readers. Its columns `json_offset`, `json_nbytes`, `json_crc32` are written since they were
added; manifests written before lack them (null where read), and `validate` then checks the member's
content against the frame's row instead of a checksum."""
STORED_MEMBERS = (*MEMBERS, FRAME_JSON)
"""Every tar member a frame may have, in column order: the array members, then the json."""
OPTIONAL_COLUMNS = frozenset(f"{FRAME_JSON}_{field}" for field in MEMBER_FIELDS)
"""Base columns that manifests written before them lack."""


def base_schema(hist_len: int) -> pa.Schema:
    """Arrow schema of the base and member columns (extra columns follow them)."""
    fields = [
        ("key", pa.string()),
        ("log", pa.string()),
        ("log_id", pa.int64()),
        ("scene_token", pa.string()),
        ("scene_name", pa.string()),
        ("frame_index", pa.int64()),
        ("token", pa.string()),
        ("timestamp_us", pa.int64()),
        ("ego_to_global", pa.list_(pa.float64(), 16)),
        ("shard", pa.string()),
        ("status", pa.string()),
        ("failure_reason", pa.string()),
        ("class_hist", pa.list_(pa.int64(), hist_len)),
        ("commit_id", pa.string()),
    ]
    for member in STORED_MEMBERS:
        fields += [
            (f"{member}_offset", pa.int64()),
            (f"{member}_nbytes", pa.int64()),
            (f"{member}_crc32", pa.uint32()),
        ]
    return pa.schema(fields)


RESERVED_COLUMNS = frozenset(base_schema(1).names)


def _infer_type(name: str, values: list) -> pa.DataType:
    """Arrow type of an extra column from its Python values (None = null)."""
    kinds = {type(v) for v in values if v is not None}
    if not kinds:
        return pa.null()
    if kinds == {bool}:
        return pa.bool_()
    if kinds == {int}:
        return pa.int64()
    if kinds <= {int, float}:
        return pa.float64()
    if kinds == {str}:
        return pa.string()
    raise InvalidFrameError(f"manifest column {name!r} mixes value types {sorted(k.__name__ for k in kinds)}")


def rows_to_table(rows: list[dict], hist_len: int) -> pa.Table:
    """Arrow table of writer rows (missing member columns become null)."""
    schema = base_schema(hist_len)
    extra = sorted({name for row in rows for name in row} - set(schema.names))
    columns = {name: [row.get(name) for row in rows] for name in (*schema.names, *extra)}
    fields = list(schema) + [pa.field(name, _infer_type(name, columns[name])) for name in extra]
    arrays = [pa.array(columns[f.name], type=f.type) for f in fields]
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def identity(table: pa.Table) -> pa.ChunkedArray:
    """The (log, token) identity of each row as one string (an unknown, null log counts as "")."""
    return pc.binary_join_element_wise(pc.fill_null(table["log"], ""), table["token"], "\x1f")


def ordered(table: pa.Table) -> pa.Table:
    """Fixed column order (base + members, then extras by name) and fixed row order."""
    n_base = len(base_schema(1))
    names = table.column_names[:n_base] + sorted(table.column_names[n_base:])
    table = table.select(names)
    return table.sort_by([(k, "ascending") for k in SORT_KEYS]).combine_chunks()


def check_unique(table: pa.Table) -> None:
    """Raise InvalidFrameError if rows repeat a (log, token) pair."""
    ids = identity(table)
    if len(pc.unique(ids)) != len(ids):
        raise InvalidFrameError("commit: the rows repeat a (log, token) pair")


def to_parquet_bytes(table: pa.Table, row_group_size: int = ROW_GROUP_SIZE) -> bytes:
    """Parquet file bytes (zstd, `row_group_size` rows per row group); equal tables give equal bytes."""
    sink = io.BytesIO()
    pq.write_table(table, sink, compression="zstd", row_group_size=row_group_size)
    return sink.getvalue()
