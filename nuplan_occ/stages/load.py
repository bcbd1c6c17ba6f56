"""load: read one scene of a log (sweeps in the ego frame, boxes, logged poses, calibration),
with context sweeps of the same log around it (aggregated, not written).

Inputs: the scene task. Outputs: `scene` (SceneData). Not cached: reading is cheaper than storing. The
sweeps' points are spilled to an unnamed file of the scene's work folder as they are read and read back
per sweep by the stages (nuplan_occ.pipeline.spilled_clouds), so no stage holds the whole scene's clouds.
A worker keeps its last log open (`nuplan_occ.io.reader.open_log`), so the scenes of one log it builds in a row read the DB once.
A sweep whose PCD is missing, corrupt, empty or outside sensor_blobs, whose pose the log cannot give
(PoseGapError), or one of whose boxes is bad is kept with its failure reason (one line); the scene goes on
without it. A scene none of whose output sweeps loaded fails at once, naming the blobs' folder and count.
The stored boxes are repaired track by track (nuplan_occ.tracks.track_repair: headings turned by 180 deg,
id switches, duplicate tracks, short gaps). A missing or unreadable map is kept as `map_problem` (the build warns once per log; the manifest's
qa_map_status carries it).
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from nuplan_occ.io.errors import MapError, MissingBlobError, NuplanFormatError, PoseGapError
from nuplan_occ.io.maps import find_map, usable_map
from nuplan_occ.io.reader import NuplanLog, SceneBoxes, open_log
from nuplan_occ.io.types import Boxes, LidarFrame, PointCloud
from nuplan_occ.pipeline.scene import SceneData, SceneTask, Sweep, output_slots
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.spilled_clouds import SpilledClouds
from nuplan_occ.pipeline.settings import settings_from
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.tracks.track_repair import TrackRepairParams, repaired_sweeps

REPAIR = TrackRepairParams  # the library's defaults


@dataclass(frozen=True)
class LoadParams:
    rate_hz: float = param(10.0, "output frame rate: every (sweep_rate_hz / rate_hz)-th sweep of the log is "
                           "written", unit="Hz", low=0.0, low_open=True)
    sweep_rate_hz: float = param(20.0, "the log's LiDAR sweep rate", unit="Hz", low=0.0, low_open=True)
    context_seconds: float = param(1.0, "sweeps of the same log this long before and after the scene are loaded "
                                   "too and aggregated, never written", unit="s", low=0.0)
    context_stride: int = param(2, "every n-th context sweep is loaded", low=1)
    heading_window_s: float = param(REPAIR.heading_window_s, "half window over which a track's boxes vote for its "
                                    "heading; a box more than 90 deg off it is turned by 180 deg (0: off)", unit="s",
                                    low=0.0)
    link_max_gap_s: float = param(REPAIR.link_max_gap_s, "a track starting at most this long after another of its "
                                  "category ended continues it (id switch; 0: off)", unit="s", low=0.0)
    link_max_distance_m: float = param(REPAIR.link_max_distance_m, "... when it starts within this distance of "
                                       "where the other's last box and velocity put it", unit="m", low=0.0)
    fill_max_gap_s: float = param(REPAIR.fill_max_gap_s, "a track's boxes missing for at most this long are "
                                  "interpolated (0: off)", unit="s", low=0.0)
    duplicate_distance_m: float = param(REPAIR.duplicate_distance_m, "a track whose boxes all lie this close to a "
                                        "longer track's of its category (and within half the narrower width) is "
                                        "dropped (0: off)", unit="m", low=0.0)

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


def read_sweep(log: NuplanLog, frame: LidarFrame, boxes: SceneBoxes, store: SpilledClouds,
               slots: dict[str, int]) -> tuple[Sweep, NuplanFormatError | None]:
    """One sweep (points spilled to `store`) and the error that failed it, if any. A sweep without a pose keeps
    the nearest usable logged pose as a stand-in (registration needs one per sweep; its points are not used)."""
    error: NuplanFormatError | None = None
    try:
        pose = log.frame_pose(frame)
    except PoseGapError as exc:
        pose, error = log.nearest_pose(frame.timestamp_us), exc
    boxes_global = Boxes.empty("global")
    cloud, dropped = None, 0
    try:
        boxes_global = boxes.of(frame)
        if error is None:
            points, lost = log.load_sweep(frame)
            cloud = store.add(compact(points.transformed(log.lidar.T_ego_from_lidar, "ego")))
            dropped = lost.total
    except NuplanFormatError as exc:
        error = error or exc
    boxes_ego = boxes_global.transformed(np.linalg.inv(pose), "ego")
    sweep = Sweep(frame.token, frame.index, frame.timestamp_us, pose, cloud, boxes_ego, boxes_global,
                  frame.token in slots, str(error) if error else "", slots.get(frame.token, -1), dropped)
    return sweep, error


def scene_failure(task: SceneTask, log: NuplanLog, frames: list[LidarFrame], sweeps: list[Sweep],
                  errors: list[NuplanFormatError | None]) -> NuplanFormatError | None:
    """The error a scene fails with when none of its output sweeps loaded (None when one did): when their blobs
    are all missing, the folder they should be in and their count; else the first error and a count per kind."""
    outputs = [(frame, error) for frame, sweep, error in zip(frames, sweeps, errors) if sweep.is_output]
    failed = [(frame, error) for frame, error in outputs if error is not None]
    if not outputs or len(failed) < len(outputs):
        return None
    if all(isinstance(error, MissingBlobError) for _, error in failed):
        folder = Path(os.path.commonpath([log.blob_path(frame).parent for frame, _ in failed]))
        state = "" if folder.is_dir() else "; the folder does not exist"
        return MissingBlobError(folder, f"{len(failed)} of the {len(outputs)} output sweeps' point cloud blobs of "
                                        f"scene {task.scene_name} are missing{state}")
    first = failed[0][1]
    kinds = ", ".join(f"{n} {kind}" for kind, n in Counter(type(e).__name__ for _, e in failed).most_common())
    return type(first)(first.path, f"none of the {len(outputs)} output sweeps of scene {task.scene_name} loaded "
                                   f"({kinds}); first: {first.problem}")


def run(inputs: dict, params: LoadParams) -> dict:
    task = inputs["task"]
    log = open_log(task.db_path, task.sensor_root)
    own = log.frames_of_scene(task.scene_token)
    slots = output_slots(own, params.rate_hz, params.sweep_rate_hz)
    frames = context_frames(log.frames, own, params.context_seconds, params.context_stride)
    boxes = log.scene_boxes(frames)
    store = SpilledClouds(task.work_dir / "load")
    read = [read_sweep(log, frame, boxes, store, slots) for frame in frames]
    sweeps, _ = repaired_sweeps([sweep for sweep, _ in read], settings_from(TrackRepairParams, params))
    failure = scene_failure(task, log, frames, sweeps, [error for _, error in read])
    if failure is not None:
        raise failure
    map_path, map_problem = usable_map(Path(task.maps_root), log.meta.map_name)
    tracks = sorted(log.tracks)
    scene = SceneData(
        task=task, meta=log.meta, sweeps=sweeps, sensor_origin_ego=log.lidar.T_ego_from_lidar[:3, 3].copy(),
        cameras=list(log.cameras), map_path=None if map_path is None else str(map_path),
        instance_ids={token: i + 1 for i, token in enumerate(tracks)},
        track_categories={token: log.tracks[token].category for token in tracks}, map_problem=map_problem,
    )
    return {"scene": scene}


def sources(task, params: LoadParams) -> list[Path]:
    """The files `run` reads for the task besides the log's DB: the point cloud blobs of the scene's sweeps and
    of its context sweeps, and the log's map file (or, without one, the maps folder it was looked for in)."""
    log = open_log(task.db_path, task.sensor_root)
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
