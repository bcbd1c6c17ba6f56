"""Content-keyed store of stage outputs under OUT/work/, written atomically.

Only files this build wrote itself are read back (zstd-compressed pickle protocol 5 of the stage
outputs, numeric arrays coded by pipeline.array_codec); nothing from the input data is ever unpickled here. A key is the sha256 of the stage name, its params, its code
version and the keys of its inputs, so a rerun finds finished work and a changed param or code reruns
only what depends on it.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import tempfile

import zstandard
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

from nuplan_occ.pipeline import array_codec

CACHE_ZSTD_LEVEL = 3
"""zstd level of cache entries (bytes and seconds per level: bench/report-manifest.md)."""

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


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write bytes to `path` via a temp file in the same folder and an atomic rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
            return pickle.loads(zstandard.ZstdDecompressor().decompress(path.read_bytes()))
        except (FileNotFoundError, pickle.UnpicklingError, zstandard.ZstdError, EOFError, AttributeError, ImportError):
            return None  # absent, or removed by another build's work-folder policy, or damaged

    def put(self, stage: str, key: str, outputs: dict[str, Any]) -> None:
        """Store outputs atomically."""
        payload = zstandard.ZstdCompressor(level=CACHE_ZSTD_LEVEL).compress(array_codec.dumps(outputs))
        atomic_write_bytes(self._path(stage, key), payload)
