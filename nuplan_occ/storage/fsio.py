"""Filesystem access for dataset roots: local paths and fsspec URLs (file://, memory://, s3://).

Publishing is atomic: on a local filesystem a file is written to a hidden temp name in the same
directory (`.<name>.tmp-<pid>-<rand>`), fsynced, then renamed over the final name; on object stores
(memory://, s3://) a single put of the whole object is atomic. Readers never look at temp names.
"""

from __future__ import annotations

import contextlib
import os
import uuid

import fsspec
import pyarrow.fs as pafs
from fsspec.implementations.local import LocalFileSystem

from nuplan_occ.storage.errors import StorageWriteError

TEMP_MARKER = ".tmp-"


def resolve(root: str) -> tuple[fsspec.AbstractFileSystem, str]:
    """(filesystem, root path without trailing slash) of a local path or fsspec URL."""
    fs, path = fsspec.core.url_to_fs(str(root))
    return fs, path.rstrip("/") or "/"


def is_local(fs: fsspec.AbstractFileSystem) -> bool:
    """True for the local filesystem, where paths are OS paths."""
    return isinstance(fs, LocalFileSystem)


def arrow_filesystem(fs: fsspec.AbstractFileSystem) -> pafs.FileSystem:
    """The pyarrow filesystem over the same files (paths as fsspec gives them)."""
    return pafs.LocalFileSystem() if is_local(fs) else pafs.PyFileSystem(pafs.FSSpecHandler(fs))


def atomic_put(fs: fsspec.AbstractFileSystem, path: str, data: bytes) -> None:
    """Publish `data` at `path` so that readers see either the old object or the whole new one.
    An OSError (disk full, quota, permissions) is raised as StorageWriteError naming `path`, after the
    local temp file is removed."""
    parent, name = path.rsplit("/", 1)
    try:
        if is_local(fs):
            tmp = f"{parent}/.{name}{TEMP_MARKER}{os.getpid()}-{uuid.uuid4().hex[:8]}"
            try:
                with _create(tmp) as f:
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.remove(tmp)
                raise
        else:
            fs.pipe_file(path, data)
    except StorageWriteError:
        raise
    except OSError as exc:
        raise StorageWriteError.of(exc, path) from exc


def _create(path: str, attempts: int = 3):
    """Open a new local file for writing, making its folder; retried when the folder vanishes in between
    (a compaction removing the folders it emptied)."""
    for attempt in range(attempts):
        os.makedirs(os.path.dirname(path), exist_ok=True)
        try:
            return open(path, "wb")
        except FileNotFoundError:
            if attempt == attempts - 1:
                raise
