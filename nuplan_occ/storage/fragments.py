"""The manifest folder: one immutable Parquet fragment per shard and commit, read as one table.

Layout under a dataset root (local path or fsspec URL):
    manifest/shards/<shard key>/<commit_id>.parquet   the rows of one shard, published by one commit
    manifest/compacted/<commit_id>.parquet             fragments folded by `nuplan-occ compact`
    manifest/scenes/<log>/<scene_token>/<commit_id>.parquet   fragments written when the unit was the scene
    manifest.parquet                                   a dataset written before fragments existed
(each "/"-separated part of <shard key> with characters outside [A-Za-z0-9_-] replaced by "_"). Every
file is published whole (temp + rename locally, one put on object stores) under a name nobody else
writes, so readers see a fragment entirely or not at all and no writer waits for another.

The unit of publication and supersession is the shard: every row, ok or failed, names its shard (the
`shard` column; a failed frame's row names the shard its chunk or scene was written to). A build
writes one shard per scene (`shards/<log>/<scene>.tar`) and a rebuilt scene rewrites the same shard
key; an import writes chunks of frames, each its own shard, and redoing a chunk rewrites it whole
under its key. Rows whose scene is unknown (null scene_token) need no scene to be published.

Commit ids are `<ns:019d>-<tiebreak:016x>`: nanoseconds since the epoch, raised to 1 ns past the
newest commit the writer can see for its shards (their shard folders and the compacted files), then 64
random bits. They sort as strings; "newest" is the greatest id. A rewrite of a shard on any machine
therefore supersedes every commit of that shard it could see, whatever the machines' clocks say; two
writers racing on one shard end with the one whose id sorts last.

Visible rows ("newest wins", `visible_rows`): for every shard key, the rows of its greatest commit id
(rows without a commit id, from a pre-fragment manifest.parquet, are older than any commit); where
two files hold that commit (a compaction that has written its output but not yet deleted its inputs)
only the first file counts. A rewrite of a shard with fewer frames hides the rest.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import time

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs
import pyarrow.parquet as pq
import fsspec

from nuplan_occ.storage.fsio import arrow_filesystem, atomic_put
from nuplan_occ.storage.manifest import to_parquet_bytes

LEGACY_MANIFEST = "manifest.parquet"
FRAGMENTS_DIR = "manifest"
SHARDS_DIR = f"{FRAGMENTS_DIR}/shards"
SCENES_DIR = f"{FRAGMENTS_DIR}/scenes"
COMPACTED_DIR = f"{FRAGMENTS_DIR}/compacted"
COMMIT_COLUMN = "commit_id"
CONTENT_KEY = b"nuplan_occ.content_sha256"
_COMMIT_ID = re.compile(r"^[0-9]{19}-[0-9a-f]{16}$")
_UNSAFE = re.compile(r"[^A-Za-z0-9_-]")


def shard_dir(root_path: str, shard: str) -> str:
    """Folder of one shard's fragments (see module docstring for the name)."""
    return f"{root_path}/{SHARDS_DIR}/" + "/".join(_UNSAFE.sub("_", part) for part in shard.split("/"))


def _commit_ids_in(fs: fsspec.AbstractFileSystem, folder: str) -> list[str]:
    """Commit ids named by the fragment files directly in `folder` (none if it does not exist)."""
    try:
        names = fs.ls(folder, detail=False)
    except FileNotFoundError:
        return []
    ids = [name.rsplit("/", 1)[-1].removesuffix(".parquet") for name in names if name.endswith(".parquet")]
    return sorted(i for i in ids if _COMMIT_ID.match(i))


def _newest_commit_under(fs: fsspec.AbstractFileSystem, folder: str) -> list[str]:
    """The greatest commit id of the fragment files anywhere under `folder` (none if it does not exist)."""
    try:
        found = fs.find(folder)
    except FileNotFoundError:
        return []
    ids = [p.rsplit("/", 1)[-1].removesuffix(".parquet") for p in found if p.endswith(".parquet")]
    return sorted(i for i in ids if _COMMIT_ID.match(i))[-1:]


def new_commit_id(fs: fsspec.AbstractFileSystem, root_path: str, folders: list[str]) -> str:
    """A commit id greater than every commit id in `folders`, the compacted files and the scene
    fragments of older datasets (see module doc; `compact` folds the latter away)."""
    seen = [i for folder in [*folders, f"{root_path}/{COMPACTED_DIR}"] for i in _commit_ids_in(fs, folder)[-1:]]
    seen += _newest_commit_under(fs, f"{root_path}/{SCENES_DIR}")
    floor = max((int(i[:19]) + 1 for i in seen), default=0)
    return f"{max(time.time_ns(), floor):019d}-{secrets.token_hex(8)}"


def content_digest(table: pa.Table) -> str:
    """sha256 of the Parquet bytes of a fragment's rows without their commit id (equal rows, equal digest)."""
    data = table.drop_columns([COMMIT_COLUMN]) if COMMIT_COLUMN in table.column_names else table
    return hashlib.sha256(to_parquet_bytes(data)).hexdigest()


def _newest_digest(fs: fsspec.AbstractFileSystem, folder: str) -> str | None:
    """Content digest stored in the newest fragment of a shard folder (None without one, or when that
    fragment cannot be read)."""
    ids = _commit_ids_in(fs, folder)
    if not ids:
        return None
    try:
        with fs.open(f"{folder}/{ids[-1]}.parquet", "rb") as handle:
            meta = pq.read_schema(handle).metadata or {}
    except (pa.ArrowInvalid, OSError):  # unreadable (readers skip it): publish the rows again
        return None
    value = meta.get(CONTENT_KEY)
    return value.decode() if value else None


def publish_fragments(fs: fsspec.AbstractFileSystem, root_path: str, table: pa.Table) -> list[str]:
    """Publish `table` (rows of one commit, any number of shards) as one fragment per shard, all with
    one new commit id; a shard whose newest fragment already holds equal rows is left as it is.
    Returns the paths written. Cost: the shards' own folders only."""
    groups = []
    for shard in sorted(pc.unique(table["shard"]).to_pylist()):
        rows = table.filter(pc.equal(table["shard"], shard)).combine_chunks()
        folder = shard_dir(root_path, shard)
        digest = content_digest(rows)
        if _newest_digest(fs, folder) != digest:
            groups.append((folder, rows, digest))
    if not groups:
        return []
    commit = new_commit_id(fs, root_path, [folder for folder, _, _ in groups])
    written = []
    for folder, rows, digest in groups:
        stamped = rows.set_column(rows.schema.get_field_index(COMMIT_COLUMN), COMMIT_COLUMN,
                                  pa.array([commit] * rows.num_rows, pa.string()))
        stamped = stamped.replace_schema_metadata({CONTENT_KEY: digest.encode()})
        path = f"{folder}/{commit}.parquet"
        atomic_put(fs, path, to_parquet_bytes(stamped))
        written.append(path)
    return written


def manifest_files(fs: fsspec.AbstractFileSystem, root_path: str) -> list[str]:
    """Every published manifest file of a root: the legacy manifest.parquet first, then compacted files,
    then scene fragments (written when the unit was the scene), then shard fragments, each group in name
    order (temp files of interrupted writes are not listed)."""
    legacy = [f"{root_path}/{LEGACY_MANIFEST}"] if fs.exists(f"{root_path}/{LEGACY_MANIFEST}") else []
    filesystem = arrow_filesystem(fs)

    def parquet_under(folder: str) -> list[str]:
        found = filesystem.get_file_info(pafs.FileSelector(folder, recursive=True, allow_not_found=True))
        return sorted(f.path for f in found if f.type == pafs.FileType.File and f.path.endswith(".parquet")
                      and not f.base_name.startswith("."))

    return legacy + [path for folder in (COMPACTED_DIR, SCENES_DIR, SHARDS_DIR)
                     for path in parquet_under(f"{root_path}/{folder}")]


def ranks_of_codes(codes: np.ndarray, dictionary: pa.Array) -> np.ndarray:
    """Rank of every row's commit id in string order (int32; null = -1, older than any commit), from
    dictionary-encoded ids: `codes` index `dictionary` (the distinct ids), -1 = null."""
    rank_of_code = np.empty(len(dictionary) + 1, dtype=np.int32)
    rank_of_code[pc.sort_indices(dictionary).to_numpy()] = np.arange(len(dictionary), dtype=np.int32)
    rank_of_code[-1] = -1
    return rank_of_code[codes]


def visible_rows(shard_codes: np.ndarray, ranks: np.ndarray, file_row_counts: np.ndarray) -> np.ndarray:
    """Bool per row: the row is visible (see module docstring). shard_codes: int codes of the shard
    column; ranks: `ranks_of_codes`; file_row_counts: rows of each file, the rows being those of the
    files in `manifest_files` order."""
    if not len(shard_codes):
        return np.zeros(0, dtype=bool)
    n_shards = int(shard_codes.max()) + 1
    newest = np.full(n_shards, -2, dtype=ranks.dtype)
    np.maximum.at(newest, shard_codes, ranks)
    keep = ranks == newest[shard_codes]
    if np.count_nonzero(file_row_counts) <= 1:
        return keep
    file_of_row = np.repeat(np.arange(len(file_row_counts), dtype=np.int32), file_row_counts)
    first_file = np.full(n_shards, np.iinfo(np.int32).max, dtype=np.int32)
    np.minimum.at(first_file, shard_codes[keep], file_of_row[keep])
    return keep & (file_of_row == first_file[shard_codes])
