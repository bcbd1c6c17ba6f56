"""`validate_dataset(root)`: every problem of a published dataset, as readable strings.

Checks dataset.json and every manifest row against the JSON Schemas (schemas/dataset_metadata.json,
schemas/manifest.json), the manifest's Arrow column types, row order and (log, token) uniqueness, and
for every ok row that its shard exists, that each member's stored bytes match the row's crc32, that
the tar header before the data names `<key>.<suffix>` (suffix as dataset.json states it), and that the
bytes decode to an array of the member's dtype and shape on the grid (`codecs.decode`). The frame's
json member gets the same checks (its crc32 column) and must parse to the identity, member suffixes
and extra columns of its row; a row written before the json columns existed has no checksum for it,
so its json member is found by name in the tar and checked by that content comparison alone (a changed
byte that still parses to equal values goes unnoticed there).
Every unreadable manifest file is a problem (one line each); the readable rest is still checked.
Leftover temp files of interrupted writes are not part of the dataset and are ignored.
"""

from __future__ import annotations

import io
import json
import tarfile
import warnings
import zlib
from collections import defaultdict
from collections.abc import Callable
from functools import lru_cache, partial

import jsonschema
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nuplan_occ import schemas
from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import codecs
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import DamagedManifestWarning, DatasetFormatError
from nuplan_occ.storage.fsio import resolve
from nuplan_occ.storage.manifest import FRAME_JSON, OPTIONAL_COLUMNS, SORT_KEYS, base_schema, identity
from nuplan_occ.storage.manifest_reader import ManifestIndex
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.writer import shard_path

MAX_REPORTED = 50
EXTRA_TYPES = (pa.bool_(), pa.int64(), pa.float64(), pa.string(), pa.null())
TAR_BLOCK = 512


@lru_cache(maxsize=None)
def _validator(schema_name: str) -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(schemas.load(schema_name))


def _schema_problems(instance: object, schema_name: str, where: str) -> list[str]:
    validator = _validator(schema_name)
    return [
        f"{where}: {'/'.join(map(str, err.absolute_path)) or '<root>'}: {err.message}"
        for err in sorted(validator.iter_errors(instance), key=lambda e: list(map(str, e.absolute_path)))
    ]


def _column_problems(table: pa.Table, hist_len: int, where: str) -> list[str]:
    problems = []
    expected = base_schema(hist_len)
    for field in expected:
        if field.name not in table.column_names:
            if field.name in OPTIONAL_COLUMNS:
                continue
            problems.append(f"{where}: missing column {field.name!r}")
        elif table.schema.field(field.name).type != field.type:
            actual = table.schema.field(field.name).type
            problems.append(f"{where}: column {field.name!r} is {actual}, expected {field.type}")
    for field in table.schema:
        if field.name not in expected.names and field.type not in EXTRA_TYPES:
            problems.append(f"{where}: extra column {field.name!r} has non-scalar type {field.type}")
    return problems


def _order_problems(table: pa.Table, where: str) -> list[str]:
    problems = []
    ids = identity(table)
    if len(pc.unique(ids)) != table.num_rows:
        problems.append(f"{where}: (log, token) pairs are not unique")
    order = pc.sort_indices(table, sort_keys=[(k, "ascending") for k in SORT_KEYS]).to_numpy()
    if not np.array_equal(order, np.arange(table.num_rows)):
        problems.append(f"{where}: rows are not sorted by {SORT_KEYS}")
    return problems


JSON_IDENTITY = ("key", "log", "log_id", "scene_token", "scene_name", "frame_index", "token", "timestamp_us",
                 "ego_to_global")
"""Fields of a frame's json member that repeat its manifest row."""


def _json_problems(blob: bytes, where: str, row: dict, suffixes: dict[str, str]) -> list[str]:
    """Problems of a frame's json member against its manifest row (see module docstring)."""
    try:
        content = json.loads(blob)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        return [f"{where}: not valid JSON ({exc})"]
    if not isinstance(content, dict):
        return [f"{where}: not a JSON object"]
    differ = [name for name in JSON_IDENTITY if content.get(name) != row.get(name)]
    members = {m: suffix for m, suffix in suffixes.items() if row.get(f"{m}_offset") is not None}
    if content.get("members") != members:
        differ.append("members")
    columns = content.get("columns")
    if not isinstance(columns, dict):
        differ.append("columns")
    else:
        differ += [f"columns/{name}" for name, value in sorted(columns.items()) if row.get(name, ...) != value]
    return [f"{where}: differs from its manifest row in {', '.join(differ)}"] if differ else []


def _member_problems(data: bytes, path: str, row: dict, member: str, suffix: str,
                     check: Callable[[bytes, str], list[str]]) -> list[str]:
    """Problems of one member whose span and crc32 the row gives; check(blob, where): its content's."""
    offset, nbytes, crc = row[f"{member}_offset"], row[f"{member}_nbytes"], row[f"{member}_crc32"]
    where = f"{path}: {row['key']}.{suffix}"
    blob = data[offset: offset + nbytes]
    if len(blob) != nbytes:
        return [f"{where}: range [{offset}, {offset + nbytes}) runs past the end of the shard ({len(data)} bytes)"]
    if crc is None:
        return [f"{where}: no crc32 in the manifest"]
    if zlib.crc32(blob) != crc:
        return [f"{where}: crc32 {zlib.crc32(blob):#010x} != manifest {crc:#010x} (checksum mismatch)"]
    problems = []
    expected_name = f"{row['key']}.{suffix}".encode()
    header_name = data[offset - TAR_BLOCK: offset - TAR_BLOCK + 100].split(b"\0", 1)[0] if offset >= TAR_BLOCK else b""
    truncated = len(header_name) == 100 and expected_name.startswith(header_name)
    if header_name != expected_name and not truncated:
        problems.append(f"{where}: tar header before offset {offset} names {header_name!r}")
    return problems + check(blob, where)


def _decode_problems(blob: bytes, where: str, member: str, grid: GridSpec) -> list[str]:
    """Problems decoding an array member's bytes to its dtype and shape on `grid`."""
    try:
        codecs.decode(MEMBERS[member], blob, grid, where)
    except DatasetFormatError as exc:
        return [str(exc)]
    return []


def _tar_spans(data: bytes, path: str) -> dict[str, tuple[int, int]] | str:
    """Member name -> (data offset, nbytes) of a shard's tar, or the problem reading it."""
    try:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
            return {m.name: (m.offset_data, m.size) for m in tar.getmembers()}
    except tarfile.TarError as exc:
        return f"{path}: tar headers unreadable ({exc})"


def _unchecksummed_json_problems(data: bytes, path: str, rows: list[dict], suffixes: dict[str, str]) -> list[str]:
    """Problems of the json members of `rows` (ok rows without json columns: manifests written before
    them), found by name in the shard's tar and compared with their rows."""
    spans = _tar_spans(data, path)
    if isinstance(spans, str):
        return [spans]
    problems = []
    for row in rows:
        name = f"{row['key']}.{FRAME_JSON}"
        if name not in spans:
            problems.append(f"{path}: {name}: member missing")
            continue
        offset, nbytes = spans[name]
        problems += _json_problems(data[offset: offset + nbytes], f"{path}: {name}", row, suffixes)
    return problems


def _shard_problems(root: str, rows: list[dict], grid: GridSpec, suffixes: dict[str, str]) -> list[str]:
    fs, path = resolve(root)
    by_shard: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        if row["status"] == "ok":
            by_shard[row["shard"]].append(row)
    problems = []
    for shard, shard_rows in sorted(by_shard.items()):
        spath = shard_path(path, shard)
        try:
            data = fs.cat_file(spath)
        except FileNotFoundError:
            problems.append(f"{spath}: shard missing ({len(shard_rows)} committed frames point to it)")
            continue
        for row in shard_rows:
            for member in MEMBERS:
                if row.get(f"{member}_offset") is not None:
                    problems += _member_problems(data, spath, row, member, suffixes[member],
                                                 partial(_decode_problems, member=member, grid=grid))
            if row.get(f"{FRAME_JSON}_offset") is not None:
                problems += _member_problems(data, spath, row, FRAME_JSON, FRAME_JSON,
                                             partial(_json_problems, row=row, suffixes=suffixes))
        older = [row for row in shard_rows if row.get(f"{FRAME_JSON}_offset") is None]
        if older:
            problems += _unchecksummed_json_problems(data, spath, older, suffixes)
    return problems


def validate_dataset(root: str) -> list[str]:
    """Problems found in the dataset at `root` (empty list: valid). See the module docstring."""
    try:
        metadata = read_metadata(root)
        with warnings.catch_warnings():  # each damaged file is reported as a problem below
            warnings.simplefilter("ignore", DamagedManifestWarning)
            index = ManifestIndex(root)
        table = index.table()
    except DatasetFormatError as exc:
        return [str(exc)]
    damaged = [file.describe() for file in index.damaged]
    problems = _schema_problems(metadata, "dataset_metadata", f"{root}/dataset.json")
    if problems:
        return damaged + problems
    grid = GridSpec.from_dict(metadata["grid"])
    where = f"{root}/manifest"
    problems += _column_problems(table, int(metadata["class_hist_length"]), where)
    problems += _order_problems(table, where)
    rows = table.to_pylist()
    for row in rows:
        problems += _schema_problems(row, "manifest", f"{where}: row {row.get('key')!r}")
        if len(problems) > MAX_REPORTED:
            return damaged + problems[:MAX_REPORTED] + ["... (stopped after the first problems)"]
    if not problems:
        suffixes = {name: entry["suffix"] for name, entry in metadata["members"].items()}
        problems += _shard_problems(root, rows, grid, suffixes)
    return damaged + problems
