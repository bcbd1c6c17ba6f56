"""Read API of a published dataset: `open_dataset(path_or_url)` -> `OccDataset`.

`ds[i]` is the i-th frame with status "ok" in manifest order (log_id, timestamp_us). Arrays are
indexed [x, y, z] in the ego frame (nuPlan rear axle at `timestamp_us`, see `nuplan_occ.grid`);
`ego_to_global` is T_global_from_ego (4, 4) float64; `flow` is m/s in the ego frame. Only the members
a frame has are returned; asking for another raises `MissingMemberError`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import MissingMemberError
from nuplan_occ.storage.manifest import MEMBER_FIELDS
from nuplan_occ.storage.manifest_reader import ManifestIndex
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.reader import BlobRequest, ShardReader, decode_request, request_of
from nuplan_occ.storage.records import STATUS_OK


def _ints(table: pa.Table, name: str) -> np.ndarray:
    """An integer column as int64 numpy, nulls as -1."""
    return table[name].cast(pa.int64()).fill_null(-1).to_numpy()


INDEX_COLUMNS = ("status", "token", "frame_index")
FRAME_COLUMNS = ("key", "shard", "token", "log", "scene_token", "timestamp_us", "frame_index", "ego_to_global")


class OccDataset:
    """Random access to the ok frames of a dataset root (local path or fsspec URL).

    Opening reads only the manifest's index columns (status, token, scene, frame index, and what
    resolving commits needs: `manifest_reader.ManifestIndex`); a frame's other columns are read when
    it is asked for. Attributes: `metadata` (dataset.json), `grid` (GridSpec), `labels` (id ->
    {"name", "color"}), `scene_codes`
    (int per frame, equal within a scene), `frame_index` (int64 per frame). `column(name)` reads one
    manifest column of every ok frame; `manifest` is the whole table of ok frames (read on first use).
    Keeps shard handles open per process.
    """

    def __init__(self, root: str):
        self.root = root
        self.metadata = read_metadata(root)
        self.grid = GridSpec.from_dict(self.metadata["grid"])
        self.labels = {
            int(c["id"]): {"name": c["name"], "color": tuple(c["color"])} for c in self.metadata["labels"]["classes"]
        }
        self._index = ManifestIndex(root)
        index = self._index.table(list(INDEX_COLUMNS))
        ok = pc.equal(index["status"], STATUS_OK).combine_chunks().fill_null(False).to_numpy(zero_copy_only=False)
        self._positions = np.flatnonzero(ok)
        index = index.filter(ok)
        self._tokens = index["token"].combine_chunks()
        self.scene_codes = self._index.scene_codes[self._positions]
        self.frame_index = _ints(index, "frame_index")
        self._manifest: pa.Table | None = None
        self._reader = ShardReader(root)

    @property
    def manifest(self) -> pa.Table:
        """Every manifest column of the ok frames, in index order (read on first use)."""
        if self._manifest is None:
            self._manifest = self._index.table(None, self._positions)
        return self._manifest

    def column(self, name: str) -> pa.Array:
        """Manifest column `name` of every ok frame, in index order (reads that column only)."""
        return self._index.column(name, self._positions)

    def has_column(self, name: str) -> bool:
        return name in self._index.schema.names

    def __len__(self) -> int:
        return self.manifest.num_rows

    def __getitem__(self, i: int) -> dict:
        return self.get(i)

    def __repr__(self) -> str:
        return f"OccDataset({self.root!r}, {len(self)} frames, grid {self.grid.shape})"

    def _check_index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames of {self.root}")
        return int(i) % n

    def _frames(self, indices: list[int], members: set[str]) -> pa.Table:
        """Identity and the spans of `members` of frames `indices` (read for these frames only)."""
        columns = [*FRAME_COLUMNS, *(f"{m}_{f}" for m in MEMBERS if m in members for f in MEMBER_FIELDS)]
        return self._index.table(columns, self._positions[np.asarray(indices, dtype=np.int64)])

    def members_of(self, i: int) -> tuple[str, ...]:
        """Members stored for frame i, in `MEMBERS` order."""
        row = self._frames([self._check_index(i)], set(MEMBERS)).to_pylist()[0]
        return tuple(m for m in MEMBERS if row[f"{m}_offset"] is not None)

    def get_many(self, indices: Sequence[int], keys: Iterable[str] | None = None) -> list[dict]:
        """Frames `indices`, each with the members `keys` (None: every member the frame has).

        The members of all frames are fetched together, so frames adjacent in a shard cost one read.
        """
        positions = [self._check_index(i) for i in indices]
        keys = tuple(keys) if keys is not None else None
        unknown = sorted(set(keys or ()) - set(MEMBERS))
        if unknown:
            raise MissingMemberError(f"unknown member {unknown[0]!r} (known: {list(MEMBERS)})")
        rows = self._frames(positions, set(keys) if keys is not None else set(MEMBERS)).to_pylist()
        wanted = [tuple(keys) if keys is not None else tuple(m for m in MEMBERS if row[f"{m}_offset"] is not None)
                  for row in rows]
        requests = [self._request(row, m) for row, members in zip(rows, wanted) for m in members]
        blobs = iter(self._reader.fetch(requests))
        reqs = iter(requests)
        frames = []
        for row, members in zip(rows, wanted):
            frame = _identity(row)
            for m in members:
                frame[m] = decode_request(next(reqs), next(blobs), self.grid)
            frames.append(frame)
        return frames

    def _request(self, row: dict, member: str) -> BlobRequest:
        if row[f"{member}_offset"] is None:
            raise MissingMemberError(f"{self.root}: frame {row['key']!r} has no {member!r} member")
        return request_of(row, member)

    def identity(self, i: int) -> dict:
        """Frame i's identity (pose, token, log, scene, timestamp, frame index) without reading a shard."""
        return _identity(self._frames([self._check_index(i)], set()).to_pylist()[0])

    def get(self, i: int, keys: Iterable[str] | None = None) -> dict:
        """Frame i with only the members `keys` (None: every member it has), plus its identity."""
        return self.get_many([i], keys)[0]

    def index_of_token(self, token: str) -> int:
        """Index of the ok frame with this lidar_pc token (KeyError if there is none)."""
        found = pc.index(self._tokens, token).as_py()
        if found < 0:
            raise KeyError(f"{self.root}: no ok frame with token {token!r}")
        return found

    def close(self) -> None:
        """Close the shard handles of this process."""
        self._reader.close()


def _identity(row: dict) -> dict:
    return {
        "ego_to_global": np.asarray(row["ego_to_global"], dtype=np.float64).reshape(4, 4),
        "token": row["token"],
        "log_name": row["log"],
        "scene_token": row["scene_token"],
        "timestamp_us": int(row["timestamp_us"]),
        "frame_index": int(row["frame_index"]),
    }


def open_dataset(path_or_url: str) -> OccDataset:
    """Open a published dataset root (local path, file://, memory://, s3:// ...)."""
    return OccDataset(path_or_url)
