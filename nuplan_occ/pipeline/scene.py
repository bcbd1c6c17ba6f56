"""The unit of work (one scene of one log) and the artifacts the first stage hands to the others."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nuplan_occ.io.types import Boxes, CameraCalibration, LogMeta, PointCloud


@dataclass(frozen=True)
class SceneTask:
    """Everything a worker needs to build one scene; plain values so it crosses process/Ray boundaries.

    out_root: dataset root (path or fsspec URL); work_root: local folder for stage outputs.
    params: stage name -> params instance.
    """

    db_path: str
    sensor_root: str
    maps_root: str
    log_name: str
    log_id: int
    scene_token: str
    scene_name: str
    out_root: str
    work_root: str
    params: dict = field(hash=False, compare=False, default_factory=dict)

    @property
    def work_dir(self) -> Path:
        """Stage outputs of this scene."""
        return Path(self.work_root) / self.log_name / self.scene_name

    @property
    def shard_key(self) -> str:
        """One tar shard per scene: shards/<log>/<scene name>.tar."""
        return f"{self.log_name}/{self.scene_name}"


def log_id_of(log_name: str) -> int:
    """Stable integer id of a log (first 8 bytes of sha256 of its name, as a non-negative int64)."""
    return int.from_bytes(hashlib.sha256(log_name.encode()).digest()[:8], "big") >> 1


def source_fingerprint(paths: list[Path]) -> str:
    """sha256 over (path, size, mtime_ns) of input files; absent files count as absent."""
    digest = hashlib.sha256()
    for path in paths:
        try:
            st = os.stat(path)
            digest.update(f"{path}|{st.st_size}|{st.st_mtime_ns}\n".encode())
        except OSError:
            digest.update(f"{path}|absent\n".encode())
    return digest.hexdigest()


@dataclass
class Sweep:
    """One 20 Hz merged LiDAR sweep of the scene.

    logged_pose: T_global_from_ego (4, 4) at the sweep's timestamp, from the log.
    cloud: points in the EGO frame of this sweep (None when the sweep failed to load: see failure).
    boxes: the sweep's boxes in its ego frame (logged pose); boxes_global as stored.
    is_output: True for the sweeps written to the dataset (the output rate, e.g. every other sweep).
    """

    token: str
    index: int
    timestamp_us: int
    logged_pose: np.ndarray
    cloud: PointCloud | None
    boxes: Boxes
    boxes_global: Boxes
    is_output: bool
    failure: str = ""


@dataclass
class SceneData:
    """A scene's inputs, read by the load stage.

    sensor_origin_ego: (3,) origin of the merged LiDAR frame in the ego frame (the rays' start point).
    instance_ids: track token -> instance id, stable over the whole log (1-based; 0 = background).
    """

    task: SceneTask
    meta: LogMeta
    sweeps: list[Sweep]
    sensor_origin_ego: np.ndarray
    cameras: list[CameraCalibration]
    map_path: str | None
    instance_ids: dict[str, int]
    track_categories: dict[str, str]

    def output_positions(self) -> list[int]:
        """Positions (in self.sweeps) of the sweeps written to the dataset, loaded or not."""
        return [i for i, sweep in enumerate(self.sweeps) if sweep.is_output]

    def ok_indices(self) -> list[int]:
        """Positions (in self.sweeps) of sweeps whose points loaded."""
        return [i for i, sweep in enumerate(self.sweeps) if sweep.cloud is not None]
