"""`DatasetWriter`: encodes frames into tar shards and commits their rows to the manifest.

Layout under the root (local path or fsspec URL):
    dataset.json                 metadata (see `metadata.py`)
    manifest/                    one immutable Parquet fragment per scene and commit (see `fragments.py`);
                                 with its rows, the commit record (see `manifest.py`)
    shards/<shard_key>.tar       WebDataset-style members `<frame_key>.<suffix>` (see `codecs.py`)
Shards, fragments and dataset.json are published atomically (`fsio.atomic_put`). A shard written but
never committed holds no frame of the dataset; rewriting a shard with equal input gives equal bytes.
Any number of writers (processes, machines) may commit into one root at once: nothing is read back but
the committed scenes' own fragment folders, so a commit costs the same at any dataset size.
"""

from __future__ import annotations

import json
import math
import re
import zlib
from collections.abc import Mapping

import numpy as np
import pyarrow as pa

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.storage import codecs
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import DatasetFormatError, InvalidFrameError
from nuplan_occ.storage.fsio import atomic_put, resolve
from nuplan_occ.storage.fragments import publish_fragments
from nuplan_occ.storage.manifest import (
    FRAME_JSON, MEMBER_FIELDS, RESERVED_COLUMNS, STORED_MEMBERS, check_unique, ordered, rows_to_table,
)
from nuplan_occ.storage.metadata import METADATA_NAME, build_metadata, label_ids, metadata_bytes
from nuplan_occ.storage.records import STATUS_FAILED, STATUS_OK, FrameRecord
from nuplan_occ.storage.tarpack import pack_tar

_SHARD_KEY = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_COLUMN_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


def shard_path(root_path: str, shard_key: str) -> str:
    """Path of a shard under a resolved root path."""
    return f"{root_path}/shards/{shard_key}.tar"


def shard_exists(root: str, shard_key: str) -> bool:
    """True if `<root>/shards/<shard_key>.tar` is published (committed or not)."""
    fs, path = resolve(root)
    return fs.exists(shard_path(path, shard_key))


def _check_shard_key(shard_key: str) -> None:
    if not isinstance(shard_key, str) or not _SHARD_KEY.match(shard_key) or any(
        part in (".", "..") for part in shard_key.split("/")
    ):
        raise InvalidFrameError(f"shard key {shard_key!r}: use [A-Za-z0-9_.-] parts joined by '/'")


def _scalar(name: str, value: object, where: str) -> float | int | bool | str | None:
    """A column value as a plain Python scalar; non-finite floats become None (null)."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    raise InvalidFrameError(f"{where}: column {name!r} has a {type(value).__name__}, expected a scalar")


def _int_or_none(value: object) -> int | None:
    return None if value is None else int(value)


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


class DatasetWriter:
    """Writes shards of `FrameRecord`s and commits their manifest rows under `root`.

    metadata: must hold "params" (any JSON); the writer adds grid, label map, member codecs, software
    and schema version. grid: the arrays' grid (default 400 x 400 x 32). zstd_levels: member name ->
    zstd level or xz preset, overriding the defaults (`codecs.MEMBERS`).
    """

    def __init__(
        self,
        root: str,
        metadata: dict,
        *,
        grid: GridSpec = DEFAULT_GRID,
        zstd_levels: Mapping[str, int] | None = None,
    ):
        unknown = sorted(set(zstd_levels or {}) - set(MEMBERS))
        if unknown:
            raise InvalidFrameError(f"zstd_levels: unknown members {unknown}")
        self.root = root
        self.grid = grid
        self.levels = {name: spec.default_level for name, spec in MEMBERS.items()} | dict(zstd_levels or {})
        self.metadata = build_metadata(metadata, grid, self.levels)
        self._fs, self._path = resolve(root)
        self._label_ids = np.array(label_ids(self.metadata["labels"]))
        self._hist_len = int(self.metadata["class_hist_length"])

    # ------------------------------------------------------------------ shards
    def write_shard(self, shard_key: str, records: list[FrameRecord]) -> list[dict]:
        """Encode `records` into `<root>/shards/<shard_key>.tar` (atomic) and return their manifest rows.

        Ok frames are stored in frame-key order, each as its array members sorted by suffix, then
        `<key>.json`; failed frames have no members (only their manifest row). The returned rows are
        plain JSON-able dicts (every manifest column present, null where absent) for `commit`.
        """
        shard = self.open_shard(shard_key)
        for record in records:
            shard.add(record)
        return shard.publish()

    def open_shard(self, shard_key: str) -> "ShardStream":
        """A shard filled one record at a time (each encoded on arrival, its arrays no longer needed), then
        published as `write_shard` would publish the same records."""
        _check_shard_key(shard_key)
        return ShardStream(self, shard_key)

    def _encode_frame(self, record: FrameRecord, shard_key: str) -> tuple[dict, list[tuple[str, bytes]]]:
        """Manifest row (offsets still missing) and tar members of one checked record."""
        where = f"shard {shard_key!r}, frame {record.key!r}"
        pose = self._check_identity(record, where)
        columns = self._check_columns(record, where)
        row: dict = {
            "key": record.key,
            "log": record.log,
            "log_id": _int_or_none(record.log_id),
            "scene_token": record.scene_token,
            "scene_name": record.scene_name,
            "frame_index": _int_or_none(record.frame_index),
            "token": record.token,
            "timestamp_us": _int_or_none(record.timestamp_us),
            "ego_to_global": None if pose is None else pose.reshape(-1).tolist(),
            "shard": shard_key,
            "status": record.status,
            "failure_reason": record.failure_reason,
            "class_hist": None,
            **{f"{name}_{field}": None for name in STORED_MEMBERS for field in MEMBER_FIELDS},
        }
        if record.status == STATUS_FAILED:
            row.update(columns)
            return row, []
        blobs: list[tuple[str, bytes]] = []
        for name in sorted(record.arrays, key=lambda n: MEMBERS[n].suffix):
            spec, array = MEMBERS[name], record.arrays[name]
            if name == "semantics":
                row["class_hist"] = self._class_hist(array, where)
            blob = codecs.encode(spec, array, self.levels[name])
            row[f"{name}_crc32"] = zlib.crc32(blob)
            blobs.append((f"{record.key}.{spec.suffix}", blob))
        frame_json = {k: row[k] for k in ("key", "log", "log_id", "scene_token", "scene_name", "frame_index",
                                          "token", "timestamp_us", "ego_to_global")}
        frame_json["members"] = {name: MEMBERS[name].suffix for name in sorted(record.arrays)}
        frame_json["columns"] = columns
        frame_json_bytes = json.dumps(frame_json, sort_keys=True, allow_nan=False).encode()
        row[f"{FRAME_JSON}_crc32"] = zlib.crc32(frame_json_bytes)
        blobs.append((f"{record.key}.{FRAME_JSON}", frame_json_bytes))
        row.update(columns)
        return row, blobs

    def _check_identity(self, record: FrameRecord, where: str) -> np.ndarray | None:
        """Check the record's identity fields and arrays; return its pose as (4, 4) float64 (None: unknown)."""
        for name in ("token", "failure_reason", "status"):
            if not isinstance(getattr(record, name), str):
                raise InvalidFrameError(f"{where}: {name} must be a str")
        for name in ("log", "scene_token", "scene_name"):
            if not isinstance(getattr(record, name), (str, type(None))):
                raise InvalidFrameError(f"{where}: {name} must be a str or None (unknown)")
        if record.log == "" or not record.token:
            raise InvalidFrameError(f"{where}: log (None when unknown) and token must not be empty")
        for name in ("log_id", "frame_index", "timestamp_us"):
            value = getattr(record, name)
            if value is not None and not _is_int(value):
                raise InvalidFrameError(f"{where}: {name} must be an int or None (unknown)")
        if any(v is not None and v < 0 for v in (record.log_id, record.frame_index)):
            raise InvalidFrameError(f"{where}: log_id and frame_index must be >= 0")
        pose = None if record.ego_to_global is None else np.asarray(record.ego_to_global, dtype=np.float64)
        if pose is not None and (pose.shape != (4, 4) or not np.all(np.isfinite(pose))):
            raise InvalidFrameError(f"{where}: ego_to_global must be a finite (4, 4) matrix or None (unknown)")
        for name, array in record.arrays.items():
            if name not in MEMBERS:
                raise InvalidFrameError(f"{where}: unknown member {name!r} (known: {list(MEMBERS)})")
            codecs.check_array(MEMBERS[name], array, self.grid, where)
        if record.status == STATUS_FAILED:
            if record.arrays or not record.failure_reason:
                raise InvalidFrameError(f"{where}: a failed frame has no arrays and a failure_reason")
        elif record.status == STATUS_OK:
            if "semantics" not in record.arrays or record.failure_reason:
                raise InvalidFrameError(f"{where}: an ok frame has semantics and no failure_reason")
        else:
            raise InvalidFrameError(f"{where}: status {record.status!r} is neither 'ok' nor 'failed'")
        return pose

    @staticmethod
    def _check_columns(record: FrameRecord, where: str) -> dict:
        """The record's extra columns as plain scalars, names checked."""
        out = {}
        for name in sorted(record.columns):
            if not isinstance(name, str) or not _COLUMN_NAME.match(name) or name in RESERVED_COLUMNS:
                raise InvalidFrameError(f"{where}: column name {name!r} is reserved or not [a-z][a-z0-9_]*")
            out[name] = _scalar(name, record.columns[name], where)
        return out

    def _class_hist(self, semantics: np.ndarray, where: str) -> list[int]:
        """Voxel count per label id; raises on ids outside the label map. Only the nonzero voxels are counted
        one by one (a grid is mostly empty)."""
        flat = semantics.reshape(-1)
        labelled = flat[flat != 0]
        hist = np.bincount(labelled, minlength=256)
        hist[0] = flat.size - labelled.size
        bad = np.setdiff1d(np.flatnonzero(hist), self._label_ids)
        if bad.size:
            raise InvalidFrameError(f"{where}: semantics holds ids {bad.tolist()} not in the label map")
        return hist[: self._hist_len].tolist()

    # ------------------------------------------------------------------ commit
    def commit(self, rows: list[dict]) -> list[str]:
        """Publish dataset.json and `rows` as one fragment per shard (the rows' `shard` column) under one
        new commit id; returns the fragment paths written.

        A shard's rows supersede every older commit of that shard (`fragments.visible_rows`), so a commit
        must hold all rows of every shard it names; a shard whose newest fragment already holds equal
        rows gets no new fragment (a rerun publishes nothing).
        dataset.json describes the build that committed last. Raises DatasetFormatError if an ok row's
        shard is missing, InvalidFrameError if rows repeat a (log, token) pair.
        """
        for shard in sorted({row["shard"] for row in rows if row.get("status") == STATUS_OK}):
            if not self._fs.exists(shard_path(self._path, shard)):
                raise DatasetFormatError(f"{shard_path(self._path, shard)}: shard of committed rows is missing")
        try:
            new = rows_to_table(rows, self._hist_len)
        except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
            raise InvalidFrameError(f"commit: rows do not fit the manifest columns: {exc}") from exc
        check_unique(new)
        atomic_put(self._fs, f"{self._path}/{METADATA_NAME}", metadata_bytes(self.metadata))
        return publish_fragments(self._fs, self._path, ordered(new)) if rows else []


class ShardStream:
    """One shard being filled by `add` (records encoded at once; only their compressed members are kept)
    and published by `publish` (frame-key order, atomic), with the same bytes as `DatasetWriter.write_shard`."""

    def __init__(self, writer: DatasetWriter, shard_key: str) -> None:
        self._writer = writer
        self._key = shard_key
        self._frames: dict[str, tuple[dict, list[tuple[str, bytes]]]] = {}

    def add(self, record: FrameRecord) -> None:
        """Check and encode one frame; raises InvalidFrameError on a bad record or a repeated frame key."""
        if record.key in self._frames:
            raise InvalidFrameError(f"shard {self._key!r}: two records share a frame key (log, frame_index)")
        self._frames[record.key] = self._writer._encode_frame(record, self._key)

    def publish(self) -> list[dict]:
        """Write the shard (atomic) and return its manifest rows, in frame-key order."""
        members: list[tuple[str, bytes]] = []
        rows = []
        for key in sorted(self._frames):
            row, frame_members = self._frames[key]
            members += frame_members
            rows.append(row)
        data, spans = pack_tar(members)
        for row in rows:
            for name in STORED_MEMBERS:
                span = spans.get(f"{row['key']}.{MEMBERS[name].suffix if name in MEMBERS else FRAME_JSON}")
                if span is not None:
                    row[f"{name}_offset"], row[f"{name}_nbytes"] = span
        atomic_put(self._writer._fs, shard_path(self._writer._path, self._key), data)
        return rows
