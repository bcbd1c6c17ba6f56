"""`compact(root)`: fold the manifest's files into one large Parquet file of its visible rows.

Steps: list the manifest files (a snapshot), read their visible rows in manifest order (commit ids
kept), publish them atomically as `manifest/compacted/<newest commit id in them>.parquet`, then delete
the snapshot's files and the local folders they leave empty. Readers see the same rows before, during
and after: while both the output and its inputs exist, resolution counts each commit once
(`fragments.visible_rows`).

Safe while writers run: a fragment committed after the snapshot is not read and not deleted, and its
commit id is newer than every commit it supersedes, whether those sit in fragments or in the compacted
file (a writer's commit id is raised past the compacted files' names). Run one compaction at a time.
A compacted pre-fragment dataset (manifest.parquet) can no longer be read by versions before fragments.

Damaged manifest files (unreadable: `manifest_reader.DamagedFile`) are never folded or deleted: the
readable files are folded as above and each damaged file stays where it is, listed in the result, so
its bytes remain for repair and a rebuild of its shard supersedes it. An output that would replace a
damaged file is refused. strict: refuse to compact at all when a manifest file is damaged.
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass, field

import pyarrow.compute as pc

from nuplan_occ.storage.errors import DatasetFormatError
from nuplan_occ.storage.fragments import COMMIT_COLUMN, COMPACTED_DIR, SCENES_DIR, SHARDS_DIR
from nuplan_occ.storage.fsio import atomic_put, is_local, resolve
from nuplan_occ.storage.manifest import to_parquet_bytes
from nuplan_occ.storage.manifest_reader import DamagedFile, ManifestIndex

COMPACTED_ROW_GROUP_SIZE = 16384


@dataclass
class CompactionResult:
    """files_before: manifest files folded; rows_before / rows_after: rows in them / visible rows kept;
    damaged: the unreadable manifest files left in place (not folded, not deleted)."""

    files_before: int
    rows_before: int
    rows_after: int
    output: str
    damaged: list[DamagedFile] = field(default_factory=list)


def compact(root: str, row_group_size: int = COMPACTED_ROW_GROUP_SIZE, *,
            strict: bool = False) -> CompactionResult:
    """Fold the manifest of `root` (see module docstring). row_group_size: rows per Parquet row group of
    the output (a random frame read costs one row group; see the manifest bench). strict: raise
    DatasetFormatError if a manifest file is damaged, before writing anything."""
    fs, path = resolve(root)
    index = ManifestIndex(root, strict=strict)
    table = index.table()
    rows_before = int(index.file_row_counts.sum())
    newest = pc.max(table[COMMIT_COLUMN]).as_py() if table.num_rows else None
    name = newest or f"{0:019d}-{secrets.token_hex(8)}"
    output = f"{path}/{COMPACTED_DIR}/{name}.parquet"
    if any(damaged.path == output for damaged in index.damaged):
        raise DatasetFormatError(f"{output}: unreadable, and the compacted manifest would replace it; "
                                 "move it aside (it may be repairable) and compact again")
    if index.paths == [output]:
        return CompactionResult(1, rows_before, table.num_rows, output, index.damaged)
    atomic_put(fs, output, to_parquet_bytes(table, row_group_size))
    for folded in index.paths:
        if folded != output:
            fs.rm_file(folded)
    if is_local(fs):
        _remove_emptied_folders(path, [p for p in index.paths if p != output])
    return CompactionResult(len(index.paths), rows_before, table.num_rows, output, index.damaged)


def _remove_emptied_folders(root_path: str, files: list[str]) -> None:
    """Remove the local folders of the folded `files` left empty, up to and including manifest/shards
    and manifest/scenes (a folder a writer has put a file in since is not empty and stays)."""
    tops = (f"{root_path}/{SHARDS_DIR}", f"{root_path}/{SCENES_DIR}")
    for folder in sorted({p.rsplit("/", 1)[0] for p in files}, key=len, reverse=True):
        while any(folder == top or folder.startswith(f"{top}/") for top in tops):
            try:
                os.rmdir(folder)
            except OSError:  # not empty, or removed already
                break
            folder = folder.rsplit("/", 1)[0]
