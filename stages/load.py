"""Stage 0, load: read one scene of a log (sweeps in the ego frame, boxes, logged poses, calibration).

Inputs: the scene task. Outputs: `scene` (SceneData). Not cached: reading is cheaper than storing.
A sweep whose PCD is missing or corrupt is kept with its failure reason; the scene goes on without it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from nuplan_occ.io.errors import NuplanFormatError
from nuplan_occ.io.maps import find_map
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.io.errors import MapError
from nuplan_occ.pipeline.scene import SceneData, Sweep
from nuplan_occ.pipeline.stage import Stage


@dataclass(frozen=True)
class LoadParams:
    """rate_hz: output frame rate; sweeps are 20 Hz, every (20 / rate_hz)-th sweep of the log is written."""

    rate_hz: float = 10.0
    sweep_rate_hz: float = 20.0


def run(inputs: dict, params: LoadParams) -> dict:
    task = inputs["task"]
    step = max(1, int(round(params.sweep_rate_hz / params.rate_hz)))
    with NuplanLog(task.db_path, task.sensor_root) as log:
        T_ego_from_lidar = log.lidar.T_ego_from_lidar
        sweeps = []
        for frame in log.frames_of_scene(task.scene_token):
            pose = log.frame_pose(frame)
            boxes_global = log.boxes(frame, "global")
            boxes_ego = log.boxes(frame, "ego")
            cloud, failure = None, ""
            try:
                cloud = log.load_points(frame).transformed(T_ego_from_lidar, "ego")
            except NuplanFormatError as exc:
                failure = str(exc)
            sweeps.append(Sweep(frame.token, frame.index, frame.timestamp_us, pose, cloud, boxes_ego,
                                boxes_global, frame.index % step == 0, failure))
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
              code=("nuplan_occ.io.reader", "nuplan_occ.io.pcd"), cache=False, doc=__doc__ or "")
