"""The unit of work (one scene of one log) and the artifacts the first stage hands to the others."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nuplan_occ.io.types import Boxes, CameraCalibration, LidarFrame, LogMeta, PointCloud
from nuplan_occ.pipeline.spilled_clouds import StoredCloud
from nuplan_occ.sequences import MappedSequence
from nuplan_occ.storage.clips import output_index_from_timestamps


@dataclass(frozen=True)
class SceneTask:
    """Everything a worker needs to build one scene; plain values so it crosses process/Ray boundaries.

    out_root: dataset root (path or fsspec URL); work_root: local folder for stage outputs.
    params: stage name -> params instance. keep_work: work-folder policy after publishing (all,
    default, none; see `pipeline.publish`), not part of any cache key.
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
    keep_work: str = "default"

    @property
    def work_dir(self) -> Path:
        """Stage outputs of this scene."""
        return Path(self.work_root) / self.log_name / self.scene_name

    @property
    def shard_key(self) -> str:
        """One tar shard per scene: shards/<log>/<scene name>.tar."""
        return f"{self.log_name}/{self.scene_name}"


def output_slots(own: list[LidarFrame], rate_hz: float, sweep_rate_hz: float) -> dict[str, int]:
    """token -> output index of a scene's output frames: its frames `own` (time order) whose log index is
    a multiple of step = round(sweep_rate_hz / rate_hz), numbered by
    `nuplan_occ.storage.clips.output_index_from_timestamps` (period step sweeps, tolerance half a sweep)."""
    step = max(1, int(round(sweep_rate_hz / rate_hz)))
    outputs = [frame for frame in own if frame.index % step == 0]
    sweep_period_us = 1e6 / sweep_rate_hz
    slots = output_index_from_timestamps(np.array([f.timestamp_us for f in outputs], dtype=np.int64),
                                         step * sweep_period_us, 0.5 * sweep_period_us)
    return {frame.token: int(slot) for frame, slot in zip(outputs, slots)}


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
    stored_cloud: where the sweep's points are kept (nuplan_occ.pipeline.spilled_clouds); None when the sweep
    failed to load (see failure). `cloud` reads them: points in the EGO frame of this sweep, xyz float32.
    boxes: the sweep's boxes in its ego frame (logged pose); boxes_global as stored.
    is_output: True for the sweeps written to the dataset (the output rate, e.g. every other sweep).
    output_index: an output sweep's index among its scene's output frames (the manifest's `output_index`,
    see `nuplan_occ.storage.clips`); -1 for the other sweeps.
    dropped_points: points of the sweep's PCD that no LiDAR can have measured, dropped on reading
    (`nuplan_occ.io.pcd.usable_points`).
    """

    token: str
    index: int
    timestamp_us: int
    logged_pose: np.ndarray
    stored_cloud: StoredCloud | None
    boxes: Boxes
    boxes_global: Boxes
    is_output: bool
    failure: str = ""
    output_index: int = -1
    dropped_points: int = 0

    @property
    def has_cloud(self) -> bool:
        """True when the sweep's points loaded."""
        return self.stored_cloud is not None

    @property
    def cloud(self) -> PointCloud | None:
        """The sweep's points, read from their store on every access (None when they failed to load)."""
        return None if self.stored_cloud is None else self.stored_cloud.read()

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) float32 points of a loaded sweep, ego frame, m (read on every access)."""
        if self.stored_cloud is None:
            raise ValueError(f"sweep {self.token} has no points: {self.failure}")
        return self.stored_cloud.field("xyz")


@dataclass
class SceneData:
    """A scene's inputs, read by the load stage.

    sensor_origin_ego: (3,) origin of the merged LiDAR frame in the ego frame (the rays' start point).
    instance_ids: track token -> instance id, stable over the whole log (1-based; 0 = background).
    map_path: the log's usable map file, None without one; map_problem: then why (one line naming the folder or
    file), "" with a map.
    """

    task: SceneTask
    meta: LogMeta
    sweeps: list[Sweep]
    sensor_origin_ego: np.ndarray
    cameras: list[CameraCalibration]
    map_path: str | None
    instance_ids: dict[str, int]
    track_categories: dict[str, str]
    map_problem: str = ""

    def output_positions(self) -> list[int]:
        """Positions (in self.sweeps) of the sweeps written to the dataset, loaded or not."""
        return [i for i, sweep in enumerate(self.sweeps) if sweep.is_output]

    def ok_indices(self) -> list[int]:
        """Positions (in self.sweeps) of sweeps whose points loaded."""
        return [i for i, sweep in enumerate(self.sweeps) if sweep.has_cloud]

    def background_positions(self, stride: int, min_sweeps: int = 0) -> list[int]:
        """Positions of the loaded sweeps to register (and, at the filter's stride, to aggregate): every output
        sweep, every `stride`-th sweep in phase with the first output sweep, and the first and last loaded
        sweeps, so that every other sweep lies between two of them. All loaded sweeps when stride is 1, or
        when the scene has fewer than `min_sweeps` loaded sweeps (a short scene keeps all its evidence)."""
        outputs, ok = self.output_positions(), self.ok_indices()
        if len(ok) < min_sweeps:
            stride = 1
        phase = outputs[0] % stride if outputs else 0
        ends = {ok[0], ok[-1]} if ok else set()
        return [i for i in ok if self.sweeps[i].is_output or i % stride == phase or i in ends]

    def spread_positions(self, stride: int, limit: int = 0) -> list[int]:
        """Every `stride`-th loaded sweep's position, thinned to at most `limit` (> 0; 0 = no limit) spread
        evenly over them, the first and last kept: evidence gathered along the whole scene at a cost that does
        not grow with its length."""
        used = self.ok_indices()[::max(1, stride)]
        if 0 < limit < len(used):
            used = [used[i] for i in np.linspace(0, len(used) - 1, limit).round().astype(int)]
        return used

    def clouds_of(self, positions: list[int]) -> MappedSequence:
        """The clouds (PointCloud, ego frame) of the sweeps at `positions`, each read when asked for."""
        return MappedSequence(list(positions), lambda position: self.sweeps[position].cloud)
