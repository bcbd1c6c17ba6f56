"""Per-scene sensor sidecars of a dataset: `<root>/sensors/<log>/<scene_token>.parquet`.

One Parquet file per scene with one row per (output frame, camera), columns `SENSOR_SCHEMA` (see
`nuplan_occ.sensors` for what each holds and how the image is matched). A sidecar rather than manifest
columns: the manifest is the commit record of the frames and is never rewritten, so a sidecar can be added
to a dataset built before sensors existed (`nuplan_occ.sensors.add_sensors`), and eight cameras per frame are
eight rows in long form, which DuckDB filters and joins on `token` as they are:
    SELECT * FROM read_parquet('out/sensors/*/*.parquet') WHERE channel = 'CAM_F0'
A dataset without sidecars has no `sensors/` folder; readers then say so (MissingSensorsError). Publishing is
atomic per file (fsio.atomic_put); a rewrite replaces the scene's file whole.
"""

from __future__ import annotations

import io
import re

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from nuplan_occ.storage import fsio
from nuplan_occ.storage.errors import DatasetFormatError, MissingMemberError

SENSORS_DIR = "sensors"

MATRIX_4 = pa.list_(pa.float64(), 16)
SENSOR_SCHEMA = pa.schema([
    ("token", pa.string()),
    ("log", pa.string()),
    ("scene_token", pa.string()),
    ("timestamp_us", pa.int64()),
    ("channel", pa.string()),
    ("camera_token", pa.string()),
    ("width", pa.int32()),
    ("height", pa.int32()),
    ("intrinsic", pa.list_(pa.float64(), 9)),
    ("distortion", pa.list_(pa.float64(), 5)),
    ("camera_to_ego", MATRIX_4),
    ("lidar_to_ego", MATRIX_4),
    ("lidar_filename", pa.string()),
    ("image_token", pa.string()),
    ("image_filename", pa.string()),
    ("image_path", pa.string()),
    ("image_timestamp_us", pa.int64()),
    ("image_ego_to_frame_ego", MATRIX_4),
])
"""Columns of a sensor sidecar (nuplan_occ.sensors documents each); image_* are null where no image matched."""

_SAFE = re.compile(r"^[A-Za-z0-9_.-]+$")


class MissingSensorsError(MissingMemberError):
    """A dataset (or one of its scenes) has no sensor metadata: built before sensors, or its log was not found
    when the sidecars were made."""


def sidecar_path(root_path: str, log: str, scene_token: str) -> str:
    """`<root_path>/sensors/<log>/<scene_token>.parquet`; DatasetFormatError for names unusable in a path."""
    for what, name in (("log", log), ("scene token", scene_token)):
        if not name or name in (".", "..") or not _SAFE.match(name):
            raise DatasetFormatError(f"{what} {name!r} cannot name a sensor sidecar file")
    return f"{root_path}/{SENSORS_DIR}/{log}/{scene_token}.parquet"


def write_sidecar(root: str, log: str, scene_token: str, table: pa.Table) -> str:
    """Publish one scene's sensor rows (SENSOR_SCHEMA, cast) atomically; returns the file's path."""
    fs, root_path = fsio.resolve(root)
    path = sidecar_path(root_path, log, scene_token)
    fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
    buffer = io.BytesIO()
    pq.write_table(table.select(SENSOR_SCHEMA.names).cast(SENSOR_SCHEMA), buffer, compression="zstd")
    fsio.atomic_put(fs, path, buffer.getvalue())
    return path


class SensorSidecars:
    """Reads the sensor sidecars of a dataset root, one scene file at a time (kept once read)."""

    def __init__(self, root: str):
        self.root = root
        self._fs, self._root_path = fsio.resolve(root)
        self._scenes: dict[tuple[str, str], dict[str, list[dict]]] = {}

    @property
    def present(self) -> bool:
        """True when the dataset has a `sensors/` folder (made by a build or by add_sensors)."""
        return self._fs.isdir(f"{self._root_path}/{SENSORS_DIR}")

    def rows(self, log: str | None, scene_token: str | None, token: str) -> list[dict]:
        """The camera rows (SENSOR_SCHEMA as Python values) of frame `token`, in the sidecar's camera order.
        MissingSensorsError when the dataset, the scene's file or the frame's rows are missing."""
        if log is None or scene_token is None:
            raise MissingSensorsError(f"{self.root}: frame {token!r} has no known log and scene, so no sensor metadata")
        if not self.present:
            raise MissingSensorsError(
                f"{self.root}: no sensor metadata (dataset built before sensors; add it with "
                "`nuplan-occ sensors <dataset> <nuPlan data root>`)")
        key = (log, scene_token)
        if key not in self._scenes:
            path = sidecar_path(self._root_path, log, scene_token)
            if not self._fs.exists(path):
                raise MissingSensorsError(f"{path}: no sensor sidecar for scene {scene_token} of log {log}")
            with self._fs.open(path, "rb") as f:
                table = pq.read_table(f)
            by_token: dict[str, list[dict]] = {}
            for row in table.to_pylist():
                by_token.setdefault(row["token"], []).append(row)
            self._scenes[key] = by_token
        rows = self._scenes[key].get(token)
        if not rows:
            raise MissingSensorsError(f"{self.root}: the sensor sidecar of scene {scene_token} has no rows for frame "
                                      f"{token!r}")
        return rows


def frame_sensors(rows: list[dict]) -> dict:
    """One frame's sidecar rows as arrays: {"lidar_to_ego": (4, 4), "lidar_filename", "cameras": {channel: {"camera_token",
    "width", "height", "intrinsic" (3, 3), "distortion" (5,), "camera_to_ego" (4, 4), "image_token",
    "image_filename", "image_path", "image_timestamp_us", "image_ego_to_frame_ego" (4, 4) or None}}}, float64."""
    def matrix(values: list | None, n: int) -> np.ndarray | None:
        return None if values is None else np.asarray(values, dtype=np.float64).reshape(n, n)

    cameras = {}
    for row in rows:
        cameras[row["channel"]] = {
            "camera_token": row["camera_token"], "width": row["width"], "height": row["height"],
            "intrinsic": matrix(row["intrinsic"], 3), "distortion": np.asarray(row["distortion"], dtype=np.float64),
            "camera_to_ego": matrix(row["camera_to_ego"], 4), "image_ego_to_frame_ego": matrix(row["image_ego_to_frame_ego"], 4),
            **{k: row[k] for k in ("image_token", "image_filename", "image_path", "image_timestamp_us")},
        }
    return {"lidar_to_ego": matrix(rows[0]["lidar_to_ego"], 4), "lidar_filename": rows[0]["lidar_filename"],
            "cameras": cameras}
