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
from collections.abc import Sequence
from dataclasses import asdict, dataclass, is_dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterator

from nuplan_occ.pipeline import array_codec
from nuplan_occ.storage.errors import StorageWriteError

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
    in the same folder, fsync, atomic rename); on error nothing is left behind, and an OSError (disk full,
    quota) becomes a StorageWriteError naming `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and not isinstance(exc, StorageWriteError):
            raise StorageWriteError.of(exc, str(path)) from exc
        raise


STREAM_BUFFER_BYTES = 1 << 20
"""Buffer between the pickler and zstd: pickle writes many small pieces."""


def _dump_frame(obj: Any, handle: BinaryIO) -> None:
    """Append one zstd frame holding `obj` (array_codec pickle) to handle, pickled straight into the stream."""
    with zstandard.ZstdCompressor(level=CACHE_ZSTD_LEVEL).stream_writer(handle, closefd=False) as raw:
        buffered = io.BufferedWriter(raw, STREAM_BUFFER_BYTES)
        array_codec.dump(obj, buffered)
        buffered.flush()


@dataclass(frozen=True)
class _ItemsRef:
    """What an entry holds in place of an output stored item by item: the frames' byte bounds in its file."""

    name: str
    bounds: tuple[int, ...]


class StoredItems(Sequence):
    """A list output of a stage kept in the cache one element per zstd frame (`<key>.<output>.items`), read
    back one element at a time on each access: a scene's per-sweep outputs never sit in memory together.
    The file is opened once, so a work-folder policy that removes it later does not break the readers.
    Pickles as a plain list."""

    def __init__(self, path: Path, bounds: tuple[int, ...]) -> None:
        self._file = open(path, "rb")
        self._bounds = bounds
        self._path = path

    def __len__(self) -> int:
        return len(self._bounds) - 1

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[j] for j in range(*k.indices(len(self)))]
        k = k + len(self) if k < 0 else k
        if not 0 <= k < len(self):
            raise IndexError(f"{self._path}: no element {k} of {len(self)}")
        start, end = self._bounds[k], self._bounds[k + 1]
        blob = os.pread(self._file.fileno(), end - start, start)
        if len(blob) != end - start:
            raise EOFError(f"{self._path}: element {k} ends at byte {start + len(blob)}, expected {end}")
        with zstandard.ZstdDecompressor().stream_reader(blob) as raw:
            return pickle.load(io.BufferedReader(raw, STREAM_BUFFER_BYTES))

    def __reduce__(self):
        return list, (list(self),)


class StageCache:
    """Stage outputs of one scene, at `<work_dir>/<stage>/<key>.pkl.zst`; an output stored item by item
    (`put`'s item_outputs) beside it, at `<key>.<output>.items`."""

    def __init__(self, work_dir: Path) -> None:
        self.work_dir = Path(work_dir)

    def _path(self, stage: str, key: str) -> Path:
        return self.work_dir / stage / f"{key}.pkl.zst"

    def _items_path(self, stage: str, key: str, name: str) -> Path:
        return self.work_dir / stage / f"{key}.{name}.items"

    def get(self, stage: str, key: str) -> dict[str, Any] | None:
        """The stored outputs, or None when absent (a damaged entry counts as absent); an output stored item
        by item comes back as a StoredItems sequence."""
        path = self._path(stage, key)
        try:
            with open(path, "rb") as handle, zstandard.ZstdDecompressor().stream_reader(handle) as raw:
                outputs = pickle.load(io.BufferedReader(raw, STREAM_BUFFER_BYTES))
            for name, value in outputs.items():
                if isinstance(value, _ItemsRef):
                    outputs[name] = self._items(stage, key, value)
            return outputs
        except (FileNotFoundError, pickle.UnpicklingError, zstandard.ZstdError, EOFError, AttributeError, ImportError):
            return None  # absent, or removed by another build's work-folder policy, or damaged

    def _items(self, stage: str, key: str, ref: _ItemsRef) -> StoredItems:
        path = self._items_path(stage, key, ref.name)
        if path.stat().st_size != ref.bounds[-1]:
            raise EOFError(f"{path}: {path.stat().st_size} bytes, the entry says {ref.bounds[-1]}")
        return StoredItems(path, ref.bounds)

    def put(self, stage: str, key: str, outputs: dict[str, Any],
            item_outputs: tuple[str, ...] = ()) -> dict[str, StoredItems]:
        """Store outputs atomically, pickled straight into the zstd stream (an entry of several GB is never
        held in memory as a whole, pickled or compressed). The outputs named in item_outputs (iterables, iterated
        once) are stored one element per frame, before the entry that points to them, so the other outputs may
        be filled while they are iterated; returns their readers."""
        stored = dict(outputs)
        for name in item_outputs:
            bounds = [0]
            with atomic_file(self._items_path(stage, key, name)) as handle:
                for item in outputs[name]:
                    _dump_frame(item, handle)
                    bounds.append(handle.tell())
            stored[name] = _ItemsRef(name, tuple(bounds))
        with atomic_file(self._path(stage, key)) as handle:
            _dump_frame(stored, handle)
        return {name: self._items(stage, key, stored[name]) for name in item_outputs}
