"""load: read one scene of a log (sweeps in the ego frame, boxes, logged poses, calibration),
with context sweeps of the same log around it (aggregated, not written).

Inputs: the scene task. Outputs: `scene` (SceneData). Not cached: reading is cheaper than storing. The
sweeps' points are spilled to an unnamed file of the scene's work folder as they are read and read back
per sweep by the stages (nuplan_occ.pipeline.spilled_clouds), so no stage holds the whole scene's clouds.
A sweep whose PCD is missing or corrupt is kept with its failure reason; the scene goes on without it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from nuplan_occ.io.errors import NuplanFormatError
from nuplan_occ.io.maps import find_map
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.io.types import LidarFrame, PointCloud
from nuplan_occ.io.errors import MapError
from nuplan_occ.pipeline.scene import SceneData, Sweep, output_slots
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.spilled_clouds import SpilledClouds
from nuplan_occ.pipeline.stage import Stage


@dataclass(frozen=True)
class LoadParams:
    rate_hz: float = param(10.0, "output frame rate: every (sweep_rate_hz / rate_hz)-th sweep of the log is "
                           "written", unit="Hz", low=0.0, low_open=True)
    sweep_rate_hz: float = param(20.0, "the log's LiDAR sweep rate", unit="Hz", low=0.0, low_open=True)
    context_seconds: float = param(1.0, "sweeps of the same log this long before and after the scene are loaded "
                                   "too and aggregated, never written", unit="s", low=0.0)
    context_stride: int = param(2, "every n-th context sweep is loaded", low=1)

    def __post_init__(self) -> None:
        if self.rate_hz > self.sweep_rate_hz:
            raise ValueError(f"rate_hz {self.rate_hz:g} exceeds the sweep rate {self.sweep_rate_hz:g} Hz")


def context_frames(log_frames: list[LidarFrame], own: list[LidarFrame], seconds: float, stride: int) -> list[LidarFrame]:
    """The scene's own frames plus, as context, every `stride`-th frame of the log (by log index) within
    `seconds` before its first or after its last frame; time order."""
    if not own or seconds <= 0:
        return list(own)
    first, last = own[0].timestamp_us, own[-1].timestamp_us
    window = int(round(seconds * 1e6))
    mine = {f.token for f in own}
    extra = [f for f in log_frames if f.token not in mine and f.index % max(1, stride) == 0
             and first - window <= f.timestamp_us <= last + window]
    return sorted([*own, *extra], key=lambda f: (f.timestamp_us, f.token))


def compact(cloud: PointCloud) -> PointCloud:
    """The sweep with float32 xyz: ego-frame points lie within ~100 m of the rear axle, where float32 rounds
    by at most 4 um, and a scene's clouds are the largest thing a build holds (bench/report-scale.md)."""
    return replace(cloud, xyz=cloud.xyz.astype(np.float32))


def run(inputs: dict, params: LoadParams) -> dict:
    task = inputs["task"]
    store = SpilledClouds(task.work_dir / "load")
    with NuplanLog(task.db_path, task.sensor_root) as log:
        T_ego_from_lidar = log.lidar.T_ego_from_lidar
        sweeps = []
        own = log.frames_of_scene(task.scene_token)
        slots = output_slots(own, params.rate_hz, params.sweep_rate_hz)
        for frame in context_frames(log.frames, own, params.context_seconds, params.context_stride):
            pose = log.frame_pose(frame)
            boxes_global = log.boxes(frame, "global")
            boxes_ego = log.boxes(frame, "ego")
            cloud, failure = None, ""
            try:
                cloud = store.add(compact(log.load_points(frame).transformed(T_ego_from_lidar, "ego")))
            except NuplanFormatError as exc:
                failure = str(exc)
            sweeps.append(Sweep(frame.token, frame.index, frame.timestamp_us, pose, cloud, boxes_ego,
                                boxes_global, frame.token in slots, failure, slots.get(frame.token, -1)))
        try:
            map_path = str(find_map(Path(task.maps_root), log.meta.map_name))
        except MapError:
            map_path = None
        tracks = sorted(log.tracks)
        scene = SceneData(
            task=task, meta=log.meta, sweeps=sweeps, sensor_origin_ego=T_ego_from_lidar[:3, 3].copy(),
            cameras=list(log.cameras), map_path=map_path,
            instance_ids={token: i + 1 for i, token in enumerate(tracks)},
            track_categories={token: log.tracks[token].category for token in tracks},
        )
    return {"scene": scene}


def sources(task, params: LoadParams) -> list[Path]:
    """The files `run` reads for the task besides the log's DB: the point cloud blobs of the scene's sweeps and
    of its context sweeps, and the log's map file (or, without one, the maps folder it was looked for in)."""
    with NuplanLog(task.db_path, task.sensor_root) as log:
        frames = context_frames(log.frames, log.frames_of_scene(task.scene_token), params.context_seconds,
                                params.context_stride)
        blobs = []
        for frame in frames:
            try:
                blobs.append(log.blob_path(frame))
            except NuplanFormatError:  # a path that is never opened: its frame fails in run
                continue
        map_name = log.meta.map_name
    try:
        map_file = find_map(Path(task.maps_root), map_name)
    except MapError:
        map_file = Path(task.maps_root) / map_name
    return [*blobs, map_file]


STAGE = Stage("load", inputs=("task",), outputs=("scene",), params_type=LoadParams, run=run, cache=False,
              sources=sources)
