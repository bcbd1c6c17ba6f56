"""write (the last frame stage): the frame's record (its arrays `members`, identity, pose, filter columns, QA
figures and status), which the runner encodes into the scene's tar shard at once (published atomically when
the scene's last frame is in; the runner commits the manifest rows). A frame whose sweep failed, or whose
earlier frame stage failed, gets a record with status "failed" and the reason.

Inputs: `scene`, `registration`, `outliers_removed` and `aggregate_outliers_removed` (qa_outliers_removed is
their sum: the sweep's points the outlier test removed, on its own or in the aggregate), `map_status`,
`map_alignment`, `object_boxes`, `object_points` (for qa_boxes_*, nuplan_occ.voxel.box_labels),
`background_positions` (for qa_ray_*: the frame's grid against the sweep between frames,
nuplan_occ.rays.frame_qa.frame_ray_columns, with the refined poses); prepared once
per scene: `ego_speeds` (F,) m/s; frame inputs `grids`, `final_semantics`, `masks`, `free_cleared`.
Frame output: `record` (FrameRecord). A row's `ego_to_global` is the refined pose corrected by the scene's
map alignment: the pose the frame's labels were rasterized with, so the map drawn with it lands where the
grid says. Instance ids and flow are 0 in the voxels the visibility stage emptied.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.rays.frame_qa import MAX_RAYS, frame_ray_columns
from nuplan_occ.pipeline.frame_columns import ego_speeds, frame_columns, point_coverage
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.storage import MEMBERS, FrameRecord
from nuplan_occ.voxel.box_labels import box_label_columns
from nuplan_occ.voxel.compose import zero_emptied_objects


@dataclass(frozen=True)
class WriteParams:
    members: tuple[str, ...] = param(("semantics", "mask_lidar", "mask_camera", "instance", "flow"),
                                     "the per-frame arrays written into the shard", choices=tuple(MEMBERS))
    ray_qa_max_rays: int = param(MAX_RAYS, "returns of the sweep between frames scored per frame for the qa_ray_* "
                                 "columns (nuplan_occ.rays.frame_qa; 0: no such columns)", low=0)


def prepare(inputs: dict, params: WriteParams) -> dict:
    """Once per scene: `ego_speeds` (F,) m/s of every sweep from its refined pose (`ego_speeds`)."""
    scene = inputs["scene"]
    return {"ego_speeds": ego_speeds(inputs["registration"].poses, np.array([s.timestamp_us for s in scene.sweeps]))}


def run(inputs: dict, frame: dict, params: WriteParams) -> dict:
    scene = inputs["scene"]
    task = scene.task
    registration = inputs["registration"]
    alignment = inputs["map_alignment"]
    position = frame["position"]
    sweep = scene.sweeps[position]
    pose = registration.poses[position] if alignment is None else alignment.correction @ registration.poses[position]
    outliers = inputs["outliers_removed"][position] + inputs["aggregate_outliers_removed"].get(position, 0)
    columns = frame_columns(scene, position, registration, inputs["ego_speeds"], outliers, inputs["map_status"],
                            alignment)
    record = FrameRecord(log=task.log_name, log_id=task.log_id, scene_token=task.scene_token,
                         scene_name=task.scene_name, frame_index=sweep.index, token=sweep.token,
                         timestamp_us=sweep.timestamp_us, ego_to_global=pose, arrays={}, columns=columns)
    if frame.get("failure"):
        record.status, record.failure_reason = "failed", frame["failure"]
        return {"record": record}
    grids, semantics = frame["grids"], frame["final_semantics"]
    zero_emptied_objects(grids, semantics)
    arrays = {"semantics": semantics, "instance": grids.instance, "flow": grids.flow, **frame["masks"]}
    record.arrays = {name: arrays[name] for name in params.members if name in arrays}
    columns["qa_point_coverage"] = point_coverage(sweep.xyz, semantics > 0)
    columns["qa_occupied_voxels"] = int(np.count_nonzero(semantics))
    columns["qa_free_space_cleared"] = int(frame["free_cleared"])
    columns["qa_unboxed_mover_voxels"] = int(grids.mover_voxels)
    columns["qa_ego_box_cleared"] = int(grids.ego_cleared)
    columns.update(box_label_columns(inputs["object_boxes"][position], inputs["object_points"][position],
                                     scene.instance_ids, semantics, grids.instance))
    if "mask_lidar" in arrays:
        columns["qa_lidar_observed_fraction"] = np.count_nonzero(arrays["mask_lidar"]) / arrays["mask_lidar"].size
    if params.ray_qa_max_rays:
        columns.update(frame_ray_columns(scene, position, registration.poses, semantics,
                                         set(inputs["background_positions"]), params.ray_qa_max_rays))
    return {"record": record}


STAGE = Stage("write", inputs=("scene", "registration", "outliers_removed", "aggregate_outliers_removed", "map_status",
                               "map_alignment", "object_boxes", "object_points", "background_positions", "grids",
                               "final_semantics", "masks", "free_cleared"),
              outputs=("record",), params_type=WriteParams, run=run, per_frame=True, prepare=prepare, kept=True)
