"""Read API of a published dataset: `open_dataset(path_or_url)` -> `OccDataset`.

`ds[i]` is the i-th frame with status "ok" in manifest order (log_id, timestamp_us). Arrays are
indexed [x, y, z] in the ego frame (nuPlan rear axle at `timestamp_us`, see `nuplan_occ.grid`);
`ego_to_global` is T_global_from_ego (4, 4) float64; `flow` is m/s in the ego frame. Only the members
a frame has are returned; asking for another raises `MissingMemberError`. Identity fields the source
did not give (an imported release without its logs) are None, and `ego_to_global` is all NaN.
An unreadable manifest file is skipped with a warning and listed in `OccDataset.damaged` (its shard's
frames fall back to the shard's previous commit, or are missing: `manifest_reader.DamagedFile`);
`strict=True` refuses to open such a dataset instead.
`sensors(i)`: frame i's camera images and calibration and the LiDAR-to-ego transform (`nuplan_occ.sensors`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pyarrow as pa

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import MissingMemberError
from nuplan_occ.storage.manifest import MEMBER_FIELDS
from nuplan_occ.storage.manifest_reader import ManifestIndex
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.reader import BlobRequest, ShardReader, decode_request, request_of
from nuplan_occ.storage.sensors import SensorSidecars, frame_sensors
from nuplan_occ.storage.token_index import TokenIndex


FRAME_COLUMNS = ("key", "shard", "token", "log", "scene_token", "timestamp_us", "frame_index", "ego_to_global")


class OccDataset:
    """Random access to the ok frames of a dataset root (local path or fsspec URL).

    Opening reads only the manifest's index columns (status, scene, frame index, and what resolving
    commits and ordering need: `manifest_reader.ManifestIndex`); a frame's other columns are read when
    it is asked for. Attributes: `metadata` (dataset.json), `grid` (GridSpec), `labels` (id ->
    {"name", "color"}), `scene_codes` (int per frame, equal within a scene), `frame_index` (int64 per
    frame, -1 where unknown), `damaged` (the manifest files skipped as unreadable, `DamagedFile` each:
    empty for an intact dataset; strict=True raises DatasetFormatError instead). `column(name)` /
    `columns(names)` read manifest columns of every ok frame; `manifest` is the whole table of ok frames
    (read on first use). Keeps shard handles open per process.
    """

    def __init__(self, root: str, *, strict: bool = False):
        self.root = root
        self.metadata = read_metadata(root)
        self.grid = GridSpec.from_dict(self.metadata["grid"])
        self.labels = {
            int(c["id"]): {"name": c["name"], "color": tuple(c["color"])} for c in self.metadata["labels"]["classes"]
        }
        self._index = ManifestIndex(root, strict=strict)
        self.damaged = self._index.damaged
        self._positions = np.flatnonzero(self._index.ok)
        self.scene_codes = self._index.scene_codes[self._positions]
        self.frame_index = self._index.frame_index[self._positions]
        self._tokens: TokenIndex | None = None
        self._manifest: pa.Table | None = None
        self._reader = ShardReader(root)
        self._sensors = SensorSidecars(root)

    @property
    def manifest(self) -> pa.Table:
        """Every manifest column of the ok frames, in index order (read on first use)."""
        if self._manifest is None:
            self._manifest = self._index.table(None, self._positions)
        return self._manifest

    def column(self, name: str) -> pa.Array:
        """Manifest column `name` of every ok frame, in index order (reads that column only)."""
        return self._index.column(name, self._positions)

    def columns(self, names: Sequence[str]) -> pa.Table:
        """Manifest columns `names` of every ok frame, in index order (one pass over the manifest files)."""
        return self._index.table(list(names), self._positions)

    def has_column(self, name: str) -> bool:
        return name in self._index.schema.names

    def __len__(self) -> int:
        return len(self._positions)

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

    def frame_key(self, i: int) -> str:
        """Frame i's key: its members are `<key>.<suffix>` in its shard."""
        return self._frames([self._check_index(i)], set()).column("key")[0].as_py()

    def get(self, i: int, keys: Iterable[str] | None = None) -> dict:
        """Frame i with only the members `keys` (None: every member it has), plus its identity."""
        return self.get_many([i], keys)[0]

    def index_of_token(self, token: str) -> int:
        """Index of the ok frame with this lidar_pc token (the first one if several; KeyError if none).
        The first call reads the token column once (`storage.token_index`); each call then reads the
        tokens of its candidates only."""
        if self._tokens is None:
            self._tokens = TokenIndex(self._index.column("token"))
        candidates = self._tokens.candidates(token)  # positions among all visible rows, ok or not
        frames = np.searchsorted(self._positions, candidates)
        is_ok = frames < len(self._positions)
        is_ok[is_ok] = self._positions[frames[is_ok]] == candidates[is_ok]
        frames = frames[is_ok]
        if len(frames):
            stored = self._index.column("token", self._positions[frames]).to_pylist()
            found = [int(i) for i, t in zip(frames, stored) if t == token]
            if found:
                return found[0]
        raise KeyError(f"{self.root}: no ok frame with token {token!r}")

    @property
    def has_sensors(self) -> bool:
        """True when the dataset has sensor metadata (`sensors/`: written by the build, or added to an older
        dataset by `nuplan_occ.sensors.add_sensors`)."""
        return self._sensors.present

    def sensors(self, i: int) -> dict:
        """Frame i's sensor metadata (`storage.sensors.frame_sensors`; fields in `nuplan_occ.sensors`):
        {"lidar_to_ego": (4, 4), "cameras": {channel: intrinsic, distortion, camera_to_ego, matched image ...}}.
        MissingSensorsError (one line) when the dataset, or the frame's scene, has none."""
        identity = self.identity(i)
        return frame_sensors(self._sensors.rows(identity["log_name"], identity["scene_token"], identity["token"]))

    def close(self) -> None:
        """Close the shard handles of this process."""
        self._reader.close()


def _identity(row: dict) -> dict:
    pose = row["ego_to_global"]
    return {
        "ego_to_global": np.full((4, 4), np.nan) if pose is None else np.asarray(pose, dtype=np.float64).reshape(4, 4),
        "token": row["token"],
        "log_name": row["log"],
        "scene_token": row["scene_token"],
        **{n: None if row[n] is None else int(row[n]) for n in ("timestamp_us", "frame_index")},
    }


def open_dataset(path_or_url: str, *, strict: bool = False) -> OccDataset:
    """Open a published dataset root (local path, file://, memory://, s3:// ...); strict: refuse a
    dataset with an unreadable manifest file (DatasetFormatError) instead of skipping it."""
    return OccDataset(path_or_url, strict=strict)
