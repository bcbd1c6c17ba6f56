"""Read API of a published dataset: `open_dataset(path_or_url)` -> `OccDataset`.

`ds[i]` is the i-th frame with status "ok" in manifest order (log_id, timestamp_us). Arrays are
indexed [x, y, z] in the ego frame (nuPlan rear axle at `timestamp_us`, see `nuplan_occ.grid`);
`ego_to_global` is T_global_from_ego (4, 4) float64; `flow` is m/s in the ego frame. Only the members
a frame has are returned; asking for another raises `MissingMemberError`. Identity fields the source
did not give (an imported release without its logs) are None, and `ego_to_global` is all NaN.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import MissingMemberError
from nuplan_occ.storage.manifest import MEMBER_FIELDS, read_manifest
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.reader import BlobRequest, ShardReader, decode_request
from nuplan_occ.storage.records import STATUS_OK


def _ints(table: pa.Table, name: str) -> np.ndarray:
    """An integer column as int64 numpy, nulls as -1."""
    return table[name].cast(pa.int64()).fill_null(-1).to_numpy()


def _poses(table: pa.Table) -> np.ndarray:
    """The ego_to_global column as (N, 4, 4) float64; null poses (unknown) are all NaN."""
    column = table["ego_to_global"].combine_chunks()
    poses = column.values.to_numpy(zero_copy_only=False).astype(np.float64).reshape(-1, 4, 4)
    poses[column.is_null().to_numpy(zero_copy_only=False)] = np.nan
    return poses


class OccDataset:
    """Random access to the ok frames of a dataset root (local path or fsspec URL).

    Attributes: `manifest` (pyarrow Table of ok frames, in index order), `metadata` (dataset.json),
    `grid` (GridSpec), `labels` (id -> {"name", "color"}). Keeps shard handles open per process.
    """

    def __init__(self, root: str):
        self.root = root
        self.metadata = read_metadata(root)
        self.grid = GridSpec.from_dict(self.metadata["grid"])
        self.labels = {
            int(c["id"]): {"name": c["name"], "color": tuple(c["color"])} for c in self.metadata["labels"]["classes"]
        }
        table = read_manifest(root)
        self.manifest = table.filter(pc.equal(table["status"], STATUS_OK)).combine_chunks()
        shard = self.manifest["shard"].combine_chunks().dictionary_encode()
        self._shard_names = shard.dictionary.to_pylist()
        self._shard_codes = shard.indices.to_numpy()
        self._spans = {
            m: np.stack([_ints(self.manifest, f"{m}_{f}") for f in MEMBER_FIELDS], axis=1)
            for m in MEMBERS
        }
        self._poses = _poses(self.manifest)
        self._ints = {n: (self.manifest[n].is_valid().to_numpy(zero_copy_only=False), _ints(self.manifest, n))
                      for n in ("timestamp_us", "frame_index")}
        self._strings = {n: self.manifest[n].combine_chunks() for n in ("key", "token", "log", "scene_token")}
        self._token_index: dict[str, int] | None = None
        self._reader = ShardReader(root)

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

    def members_of(self, i: int) -> tuple[str, ...]:
        """Members stored for frame i, in `MEMBERS` order."""
        i = self._check_index(i)
        return tuple(m for m in MEMBERS if self._spans[m][i, 0] >= 0)

    def _request(self, i: int, member: str) -> BlobRequest:
        if member not in MEMBERS:
            raise MissingMemberError(f"unknown member {member!r} (known: {list(MEMBERS)})")
        offset, nbytes, crc = self._spans[member][i]
        key = self._strings["key"][i].as_py()
        if offset < 0:
            raise MissingMemberError(f"{self.root}: frame {key!r} has no {member!r} member")
        return BlobRequest(self._shard_names[self._shard_codes[i]], int(offset), int(nbytes), int(crc), key, member)

    def _identity(self, i: int) -> dict:
        return {
            "ego_to_global": self._poses[i].copy(),
            "token": self._strings["token"][i].as_py(),
            "log_name": self._strings["log"][i].as_py(),
            "scene_token": self._strings["scene_token"][i].as_py(),
            **{n: int(values[i]) if known[i] else None for n, (known, values) in self._ints.items()},
        }

    def get_many(self, indices: Sequence[int], keys: Iterable[str] | None = None) -> list[dict]:
        """Frames `indices`, each with the members `keys` (None: every member the frame has).

        The members of all frames are fetched together, so frames adjacent in a shard cost one read.
        """
        rows = [self._check_index(i) for i in indices]
        wanted = [tuple(keys) if keys is not None else self.members_of(i) for i in rows]
        requests = [self._request(i, m) for i, members in zip(rows, wanted) for m in members]
        blobs = iter(self._reader.fetch(requests))
        reqs = iter(requests)
        frames = []
        for i, members in zip(rows, wanted):
            frame = self._identity(i)
            for m in members:
                frame[m] = decode_request(next(reqs), next(blobs), self.grid)
            frames.append(frame)
        return frames

    def get(self, i: int, keys: Iterable[str] | None = None) -> dict:
        """Frame i with only the members `keys` (None: every member it has), plus its identity."""
        return self.get_many([i], keys)[0]

    def index_of_token(self, token: str) -> int:
        """Index of the ok frame with this lidar_pc token (KeyError if there is none)."""
        if self._token_index is None:
            self._token_index = {t: i for i, t in enumerate(self._strings["token"].to_pylist())}
        try:
            return self._token_index[token]
        except KeyError:
            raise KeyError(f"{self.root}: no ok frame with token {token!r}") from None

    def close(self) -> None:
        """Close the shard handles of this process."""
        self._reader.close()


def open_dataset(path_or_url: str) -> OccDataset:
    """Open a published dataset root (local path, file://, memory://, s3:// ...)."""
    return OccDataset(path_or_url)
