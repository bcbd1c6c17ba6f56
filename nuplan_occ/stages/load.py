"""Stage 0, load: read one scene of a log (sweeps in the ego frame, boxes, logged poses, calibration),
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
from nuplan_occ.pipeline.spilled_clouds import SpilledClouds
from nuplan_occ.pipeline.stage import Stage


@dataclass(frozen=True)
class LoadParams:
    """rate_hz: output frame rate; sweeps are 20 Hz, every (20 / rate_hz)-th sweep of the log is written.
    context_seconds: sweeps of the same log this long before and after the scene are loaded too (every
    context_stride-th one) and aggregated, never written: objects and ground seen from more viewpoints, and
    the first and last frames of a scene get context on both sides. Measured on the synthetic `small` preset
    (0.8 s scenes of a 4 s log): ..."""

    rate_hz: float = 10.0
    sweep_rate_hz: float = 20.0
    context_seconds: float = 1.0
    context_stride: int = 2


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


STAGE = Stage("load", inputs=("task",), outputs=("scene",), params_type=LoadParams, run=run,
              code=("nuplan_occ.io.reader", "nuplan_occ.io.pcd", "nuplan_occ.pipeline.spilled_clouds"), cache=False,
              doc=__doc__ or "")
