"""The report's view of a dataset: every manifest row (failed ones included) as numpy columns, ordered by
scene then time, with the scenes as contiguous row ranges. Read through the storage reader API
(`nuplan_occ.storage.manifest_reader.ManifestIndex`, only the columns the report shows), never from the
files themselves.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nuplan_occ.evaluation.ray_qa import sidecar_columns
from nuplan_occ.report.flags import Columns
from nuplan_occ.storage import MEMBERS
from nuplan_occ.storage.manifest_reader import ManifestIndex
from nuplan_occ.storage.records import STATUS_OK

IDENTITY = ("log", "scene_token", "scene_name", "frame_index", "token", "timestamp_us", "status", "failure_reason")


def column_to_numpy(column: pa.ChunkedArray) -> np.ndarray:
    """A scalar column as numpy: bool (null False), float64 (null NaN), else object strings (null "")."""
    if pa.types.is_boolean(column.type):
        return column.fill_null(False).to_numpy(zero_copy_only=False).astype(bool)
    if pa.types.is_integer(column.type) or pa.types.is_floating(column.type):
        return column.cast(pa.float64()).fill_null(float("nan")).to_numpy(zero_copy_only=False)
    if pa.types.is_null(column.type):
        return np.full(len(column), np.nan)
    return column.cast(pa.string()).fill_null("").to_numpy(zero_copy_only=False)


@dataclass
class BuildFrames:
    """columns: identity columns (as strings / float), every `qa_*` column (the ray-consistency ones from
    `nuplan-occ qa`'s sidecar files when the manifest lacks them), `nbytes` (stored bytes of the frame, all
    members); poses (N, 4, 4) T_global_from_ego; class_hist (N, K) voxels per label id; ok (N,) bool;
    scenes: (start, stop) row ranges, one per scene, in (log, scene name) order."""

    columns: Columns
    poses: np.ndarray
    class_hist: np.ndarray
    ok: np.ndarray
    scenes: list[tuple[int, int]]

    def __len__(self) -> int:
        return len(self.ok)

    def scene_key(self, start: int, stop: int) -> str:
        """sha256 over every column's values of the scene's rows: equal rows, equal key."""
        digest = hashlib.sha256()
        for name in sorted(self.columns):
            values = self.columns[name][start:stop]
            digest.update(name.encode())
            digest.update(json.dumps(values.tolist(), default=str).encode() if values.dtype == object
                          else np.ascontiguousarray(values).tobytes())
        digest.update(self.poses[start:stop].tobytes())
        digest.update(self.class_hist[start:stop].tobytes())
        return digest.hexdigest()


def _member_bytes(table: pa.Table) -> np.ndarray:
    total = np.zeros(table.num_rows, dtype=np.float64)
    for member in MEMBERS:
        name = f"{member}_nbytes"
        if name in table.column_names:
            total += table[name].cast(pa.float64()).fill_null(0.0).to_numpy(zero_copy_only=False)
    return total


def load_frames(root: str) -> BuildFrames:
    """Every row of the dataset at `root`, ordered by (log, scene name, timestamp)."""
    index = ManifestIndex(root)
    available = index.schema.names
    wanted = [*IDENTITY, "ego_to_global", "class_hist", "commit_id", *(f"{m}_nbytes" for m in MEMBERS),
              *(n for n in available if n.startswith("qa_"))]
    table = index.table([n for n in wanted if n in available])
    table = table.sort_by([("log", "ascending"), ("scene_name", "ascending"), ("timestamp_us", "ascending")])
    names = [*IDENTITY, *sorted(n for n in table.column_names if n.startswith("qa_"))]
    columns = {name: column_to_numpy(table[name]) for name in names}
    columns["nbytes"] = _member_bytes(table)
    if "qa_ray_agree" not in columns and "commit_id" in table.column_names:  # `nuplan-occ qa`'s files, if any
        columns.update(sidecar_columns(root, columns["token"], column_to_numpy(table["commit_id"])))
    n = table.num_rows
    poses = table["ego_to_global"].combine_chunks().values.to_numpy(zero_copy_only=False).reshape(n, 4, 4)
    hist = table["class_hist"].combine_chunks()
    class_hist = hist.values.fill_null(0).to_numpy(zero_copy_only=False).reshape(n, hist.type.list_size).copy()
    class_hist[~hist.is_valid().to_numpy(zero_copy_only=False)] = 0  # a failed frame has no histogram
    scene = columns["scene_token"]
    starts = np.flatnonzero(np.r_[True, scene[1:] != scene[:-1]]) if n else np.zeros(0, dtype=int)
    stops = np.r_[starts[1:], n]
    ok = pc.equal(table["status"], STATUS_OK).fill_null(False).to_numpy(zero_copy_only=False).astype(bool)
    return BuildFrames(columns, poses, class_hist.astype(np.int64), ok, list(zip(starts.tolist(), stops.tolist())))
