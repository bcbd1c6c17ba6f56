"""Content-keyed store of stage outputs under OUT/work/, written atomically.

Only files this build wrote itself are read back (zstd-compressed pickle protocol 5 of the stage
outputs, numeric arrays coded by pipeline.array_codec); nothing from the input data is ever unpickled here. A key is the sha256 of the stage name, its params, its code
version and the keys of its inputs, so a rerun finds finished work and a changed param or code reruns
only what depends on it.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import tempfile
from contextlib import contextmanager

import zstandard
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterator

from nuplan_occ.pipeline import array_codec

CACHE_ZSTD_LEVEL = 3
"""zstd level of cache entries (bytes and seconds per level: the notes of bench/report-scale.md)."""

def stable_hash(*parts: Any) -> str:
    """sha256 hex of JSON-serialisable parts (dataclasses are turned into dicts)."""
    def encode(obj: Any) -> Any:
        if is_dataclass(obj) and not isinstance(obj, type):
            return {"__type__": type(obj).__name__, **{k: encode(v) for k, v in asdict(obj).items()}}
        if isinstance(obj, dict):
            return {str(k): encode(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
        if isinstance(obj, (list, tuple)):
            return [encode(v) for v in obj]
        return obj

    return hashlib.sha256(json.dumps(encode(parts), sort_keys=True, default=str).encode()).hexdigest()


@contextmanager
def atomic_file(path: Path) -> Iterator[BinaryIO]:
    """A file handle whose content appears at `path` only when the block ends without error (temp file
    in the same folder, fsync, atomic rename); on error nothing is left behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


STREAM_BUFFER_BYTES = 1 << 20
"""Buffer between the pickler and zstd: pickle writes many small pieces."""


class StageCache:
    """Stage outputs of one scene, at `<work_dir>/<stage>/<key>.pkl.zst`."""

    def __init__(self, work_dir: Path) -> None:
        self.work_dir = Path(work_dir)

    def _path(self, stage: str, key: str) -> Path:
        return self.work_dir / stage / f"{key}.pkl.zst"

    def get(self, stage: str, key: str) -> dict[str, Any] | None:
        """The stored outputs, or None when absent (a damaged entry counts as absent)."""
        path = self._path(stage, key)
        try:
            with open(path, "rb") as handle, zstandard.ZstdDecompressor().stream_reader(handle) as raw:
                return pickle.load(io.BufferedReader(raw, STREAM_BUFFER_BYTES))
        except (FileNotFoundError, pickle.UnpicklingError, zstandard.ZstdError, EOFError, AttributeError, ImportError):
            return None  # absent, or removed by another build's work-folder policy, or damaged

    def put(self, stage: str, key: str, outputs: dict[str, Any]) -> None:
        """Store outputs atomically, pickled straight into the zstd stream (an entry of several GB is never
        held in memory as a whole, pickled or compressed)."""
        with atomic_file(self._path(stage, key)) as handle:
            with zstandard.ZstdCompressor(level=CACHE_ZSTD_LEVEL).stream_writer(handle, closefd=False) as raw:
                buffered = io.BufferedWriter(raw, STREAM_BUFFER_BYTES)
                array_codec.dump(outputs, buffered)
                buffered.flush()
