"""The manifest folder: one immutable Parquet fragment per scene and commit, read as one table.

Layout under a dataset root (local path or fsspec URL):
    manifest/scenes/<log>/<scene_token>/<commit_id>.parquet   the rows of one scene, published by one commit
    manifest/compacted/<commit_id>.parquet                     fragments folded by `nuplan-occ compact`
    manifest.parquet                                           a dataset written before fragments existed
(<log> with characters outside [A-Za-z0-9_-] replaced by "_"). Every file is published whole (temp +
rename locally, one put on object stores) under a name nobody else writes, so readers see a fragment
entirely or not at all and no writer waits for another.

Commit ids are `<ns:019d>-<tiebreak:016x>`: nanoseconds since the epoch, raised to 1 ns past the
newest commit the writer can see for its scenes (their scene folders and the compacted files), then 64
random bits. They sort as strings; "newest" is the greatest id. A rebuild of a scene on any machine
therefore supersedes every commit of that scene it could see, whatever the machines' clocks say; two
writers racing on one scene end with the one whose id sorts last.

Visible rows ("newest wins", `visible_rows`): for every scene_token, the rows of its greatest commit id
(rows without a commit id, from a pre-fragment manifest.parquet, are older than any commit); where
two files hold that commit (a compaction that has written its output but not yet deleted its inputs)
only the first file counts. The unit is the scene: a rebuild that writes fewer frames hides the rest.
"""

from __future__ import annotations

import hashlib
import re
import secrets
import time

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import fsspec

from nuplan_occ.storage.fsio import atomic_put
from nuplan_occ.storage.manifest import to_parquet_bytes

LEGACY_MANIFEST = "manifest.parquet"
FRAGMENTS_DIR = "manifest"
SCENES_DIR = f"{FRAGMENTS_DIR}/scenes"
COMPACTED_DIR = f"{FRAGMENTS_DIR}/compacted"
COMMIT_COLUMN = "commit_id"
CONTENT_KEY = b"nuplan_occ.content_sha256"
_COMMIT_ID = re.compile(r"^[0-9]{19}-[0-9a-f]{16}$")
_UNSAFE = re.compile(r"[^A-Za-z0-9_-]")


def scene_dir(root_path: str, log: str, scene_token: str) -> str:
    """Folder of one scene's fragments."""
    return f"{root_path}/{SCENES_DIR}/{_UNSAFE.sub('_', log)}/{_UNSAFE.sub('_', scene_token)}"


def _commit_ids_in(fs: fsspec.AbstractFileSystem, folder: str) -> list[str]:
    """Commit ids named by the fragment files directly in `folder` (none if it does not exist)."""
    try:
        names = fs.ls(folder, detail=False)
    except FileNotFoundError:
        return []
    ids = [name.rsplit("/", 1)[-1].removesuffix(".parquet") for name in names if name.endswith(".parquet")]
    return sorted(i for i in ids if _COMMIT_ID.match(i))


def new_commit_id(fs: fsspec.AbstractFileSystem, root_path: str, folders: list[str]) -> str:
    """A commit id greater than every commit id in `folders` and the compacted files (see module doc)."""
    seen = [i for folder in [*folders, f"{root_path}/{COMPACTED_DIR}"] for i in _commit_ids_in(fs, folder)[-1:]]
    floor = max((int(i[:19]) + 1 for i in seen), default=0)
    return f"{max(time.time_ns(), floor):019d}-{secrets.token_hex(8)}"


def content_digest(table: pa.Table) -> str:
    """sha256 of the Parquet bytes of a fragment's rows without their commit id (equal rows, equal digest)."""
    data = table.drop_columns([COMMIT_COLUMN]) if COMMIT_COLUMN in table.column_names else table
    return hashlib.sha256(to_parquet_bytes(data)).hexdigest()


def _newest_digest(fs: fsspec.AbstractFileSystem, folder: str) -> str | None:
    """Content digest stored in the newest fragment of a scene folder (None without one)."""
    ids = _commit_ids_in(fs, folder)
    if not ids:
        return None
    with fs.open(f"{folder}/{ids[-1]}.parquet", "rb") as handle:
        meta = pq.read_schema(handle).metadata or {}
    value = meta.get(CONTENT_KEY)
    return value.decode() if value else None


def publish_fragments(fs: fsspec.AbstractFileSystem, root_path: str, table: pa.Table) -> list[str]:
    """Publish `table` (rows of one commit, any number of scenes) as one fragment per scene, all with
    one new commit id; a scene whose newest fragment already holds equal rows is left as it is.
    Returns the paths written. Cost: the scenes' own folders only."""
    scenes = pc.unique(table["scene_token"]).to_pylist()
    groups = []
    for scene_token in sorted(scenes):
        rows = table.filter(pc.equal(table["scene_token"], scene_token)).combine_chunks()
        log = rows["log"][0].as_py()
        folder = scene_dir(root_path, log, scene_token)
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
    then scene fragments, each group in name order (temp files of interrupted writes are not listed)."""
    legacy = [f"{root_path}/{LEGACY_MANIFEST}"] if fs.exists(f"{root_path}/{LEGACY_MANIFEST}") else []

    def parquet_under(folder: str) -> list[str]:
        try:
            found = fs.find(folder)
        except FileNotFoundError:
            return []
        return sorted(p for p in found if p.endswith(".parquet") and not p.rsplit("/", 1)[-1].startswith("."))

    return legacy + parquet_under(f"{root_path}/{COMPACTED_DIR}") + parquet_under(f"{root_path}/{SCENES_DIR}")


def commit_ranks(commit_ids: pa.ChunkedArray | pa.Array) -> np.ndarray:
    """Rank of every row's commit id in string order (int64; null = -1, older than any commit)."""
    if isinstance(commit_ids, pa.ChunkedArray):
        commit_ids = commit_ids.combine_chunks()
    encoded = pc.dictionary_encode(commit_ids)
    rank_of_code = np.empty(len(encoded.dictionary), dtype=np.int64)
    rank_of_code[pc.sort_indices(encoded.dictionary).to_numpy()] = np.arange(len(encoded.dictionary))
    codes = encoded.indices.fill_null(-1).to_numpy().astype(np.int64)
    ranks = np.full(len(codes), -1, dtype=np.int64)
    ranks[codes >= 0] = rank_of_code[codes[codes >= 0]]
    return ranks


def visible_rows(scene_codes: np.ndarray, ranks: np.ndarray, file_of_row: np.ndarray) -> np.ndarray:
    """Bool per row: the row is visible (see module docstring). scene_codes: int codes of scene_token;
    ranks: `commit_ranks`; file_of_row: index of the file holding the row (files in `manifest_files` order)."""
    if not len(scene_codes):
        return np.zeros(0, dtype=bool)
    n_scenes = int(scene_codes.max()) + 1
    newest = np.full(n_scenes, -2, dtype=np.int64)
    np.maximum.at(newest, scene_codes, ranks)
    keep = ranks == newest[scene_codes]
    first_file = np.full(n_scenes, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(first_file, scene_codes[keep], file_of_row[keep])
    return keep & (file_of_row == first_file[scene_codes])
