"""Stage 10, write: one tar shard per scene (semantics, masks, instance, flow per frame, zstd) published
atomically, and the scene's manifest rows (identity, pose, filter columns, QA figures, status). Frames
whose sweep failed get a row with status "failed" and the reason. The runner commits the rows.

Inputs: `scene`, `registration`, `grids`, `final_semantics`, `masks`, `free_cleared`, `outliers_removed`,
`map_status`, `map_alignment`, `object_boxes`, `object_points` (for qa_boxes_*, `nuplan_occ.voxel.box_labels`).
Outputs: `rows` (manifest rows of the scene). A row's `ego_to_global` is the refined pose corrected by the
scene's map alignment: the pose the frame's labels were rasterized with, so the map drawn with it lands
where the grid says.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.pipeline.frame_columns import agent_speed_columns, ego_speeds, point_coverage
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.storage import DatasetWriter, FrameRecord
from nuplan_occ.voxel.box_labels import box_label_columns
from nuplan_occ.voxel.map_align import MapAlignment


@dataclass(frozen=True)
class WriteParams:
    """members: which per-frame arrays go into the shard."""

    members: tuple[str, ...] = ("semantics", "mask_lidar", "mask_camera", "instance", "flow")


def frame_columns(scene, position: int, registration, speeds, outliers: int, map_status: str,
                  alignment: MapAlignment | None) -> dict:
    """output_index (see `nuplan_occ.storage.clips`), filter columns and QA figures of one frame (qa_map_*: the
    scene's map alignment, NaN without)."""
    sweep = scene.sweeps[position]
    correction = invert_transform(sweep.logged_pose) @ registration.poses[position]  # in the logged ego frame
    columns = {
        "output_index": int(sweep.output_index),
        "ego_speed": float(speeds[position]),
        **agent_speed_columns(sweep.boxes_global),
        "qa_pose_correction_m": float(np.linalg.norm(correction[:3, 3])),
        "qa_pose_correction_deg": float(np.degrees(np.arccos(np.clip((np.trace(correction[:3, :3]) - 1) / 2, -1, 1)))),
        "qa_pose_accepted": bool(registration.accepted[position]),
        "qa_pose_fitness": float(registration.fitness[position]),
        "qa_points": len(sweep.cloud) if sweep.cloud is not None else 0,
        "qa_outliers_removed": int(outliers),
        "qa_map_status": map_status,
        "qa_map_aligned": bool(alignment is not None and alignment.applied),
        "qa_map_offset_m": float(np.hypot(alignment.dx, alignment.dy)) if alignment is not None else float("nan"),
        "qa_map_yaw_deg": float(np.degrees(alignment.dyaw)) if alignment is not None else float("nan"),
        "qa_map_paint_points": int(alignment.n_points) if alignment is not None else 0,
        "qa_map_paint_rms_m": float(alignment.rms_after) if alignment is not None else float("nan"),
    }
    return columns


def run(inputs: dict, params: WriteParams) -> dict:
    scene = inputs["scene"]
    task = scene.task
    registration = inputs["registration"]
    alignment = inputs["map_alignment"]
    poses = registration.poses
    map_poses = poses if alignment is None else np.einsum("ij,njk->nik", alignment.correction, poses)
    speeds = ego_speeds(poses, np.array([s.timestamp_us for s in scene.sweeps]))
    records = []
    for position, sweep in enumerate(scene.sweeps):
        if not sweep.is_output:
            continue
        columns = frame_columns(scene, position, registration, speeds, inputs["outliers_removed"][position],
                                inputs["map_status"], alignment)
        record = FrameRecord(log=task.log_name, log_id=task.log_id, scene_token=task.scene_token,
                             scene_name=task.scene_name, frame_index=sweep.index, token=sweep.token,
                             timestamp_us=sweep.timestamp_us, ego_to_global=map_poses[position], arrays={},
                             columns=columns)
        if sweep.token not in inputs["final_semantics"]:
            record.status, record.failure_reason = "failed", sweep.failure or "frame was not built"
            records.append(record)
            continue
        grids = inputs["grids"][sweep.token]
        semantics = inputs["final_semantics"][sweep.token]
        arrays = {"semantics": semantics, "instance": grids.instance, "flow": grids.flow,
                  **inputs["masks"].get(sweep.token, {})}
        record.arrays = {name: arrays[name] for name in params.members if name in arrays}
        columns["qa_point_coverage"] = point_coverage(sweep.cloud.xyz, semantics > 0)
        columns["qa_occupied_voxels"] = int((semantics > 0).sum())
        columns["qa_free_space_cleared"] = int(inputs["free_cleared"].get(sweep.token, 0))
        columns.update(box_label_columns(inputs["object_boxes"][position], inputs["object_points"][position],
                                         scene.instance_ids, semantics, grids.instance))
        if "mask_lidar" in arrays:
            columns["qa_lidar_observed_fraction"] = float(arrays["mask_lidar"].mean())
        records.append(record)
    writer = DatasetWriter(task.out_root, metadata={"params": {}})
    return {"rows": writer.write_shard(task.shard_key, records)}


STAGE = Stage("write", inputs=("scene", "registration", "grids", "final_semantics", "masks", "free_cleared",
                                "outliers_removed", "map_status", "map_alignment", "object_boxes", "object_points"),
              outputs=("rows",), params_type=WriteParams, run=run,
              code=("nuplan_occ.storage", "nuplan_occ.voxel.box_labels"), doc=__doc__ or "")
