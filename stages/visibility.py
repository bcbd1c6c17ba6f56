"""Stage 9, visibility: `mask_lidar` by casting the frame's own LiDAR rays through the grid (voxels
traversed = observed free, the return voxel = observed occupied, the rest unknown); free-space
consistency: background voxels those rays crossed, with no aggregated point in them, above the ground
voxel, are cleared (nuplan_occ.voxel.free_space); then `mask_camera` from the 8 cameras' frusta with
occlusion by the frame's (cleared) occupancy.

Rays start at the merged LiDAR frame's origin (the only sensor pose nuPlan stores).
Inputs: `scene`, `registration`, `background_aggregate`, `grids`, `semantics`. Outputs: `masks` (sweep
token -> {"mask_lidar", "mask_camera"}), `final_semantics` (sweep token -> uint8 grid: `semantics` with the
cleared voxels empty), `free_cleared` (sweep token -> number of voxels cleared).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.voxel.free_space import point_support, unsupported_free_voxels
from nuplan_occ.voxel.visibility import UNKNOWN, camera_visibility, lidar_observation


@dataclass(frozen=True)
class VisibilityParams:
    """camera_max_range_m: farthest distance a camera is taken to observe. clear_free_space: clear
    background voxels the frame's rays show empty (needs `lidar`); free_space_ground_margin_m: only voxels
    whose centre is this far above the local ground (0.2 m: the ground voxel is never cleared). Measured on
    the bench build: trail voxels 133 -> 23, mIoU 0.758 -> 0.764, occupied IoU 0.926 -> 0.925, ground
    holes unchanged (margin 0.125 m the same, 0.3 m clears too little: 100 trails)."""

    lidar: bool = True
    camera: bool = True
    camera_max_range_m: float = 60.0
    clear_free_space: bool = True
    free_space_ground_margin_m: float = 0.2


def run(inputs: dict, params: VisibilityParams) -> dict:
    scene = inputs["scene"]
    poses = inputs["registration"].poses
    background = inputs["background_aggregate"]
    masks, final, cleared = {}, {}, {}
    for position, sweep in enumerate(scene.sweeps):
        if sweep.token not in inputs["semantics"]:
            continue
        semantics = inputs["semantics"][sweep.token].copy()
        masks[sweep.token] = {}
        cleared[sweep.token] = 0
        if params.lidar:
            observation = lidar_observation(sweep.cloud.xyz, scene.sensor_origin_ego, DEFAULT_GRID)
            masks[sweep.token]["mask_lidar"] = observation != UNKNOWN
            if params.clear_free_space:
                grids = inputs["grids"][sweep.token]
                support = point_support(transform_points(invert_transform(poses[position]) @ background.T_global_from_scene,
                                                         background.points), DEFAULT_GRID)
                clear = unsupported_free_voxels(grids.occupied_background & (semantics > 0), observation, support,
                                                grids.ground_height, DEFAULT_GRID, params.free_space_ground_margin_m)
                semantics[clear] = 0
                cleared[sweep.token] = int(clear.sum())
        final[sweep.token] = semantics
        if params.camera and scene.cameras:
            masks[sweep.token]["mask_camera"] = camera_visibility(
                semantics > 0, scene.cameras, DEFAULT_GRID, max_range_m=params.camera_max_range_m)
    return {"masks": masks, "final_semantics": final, "free_cleared": cleared}


STAGE = Stage("visibility", inputs=("scene", "registration", "background_aggregate", "grids", "semantics"),
              outputs=("masks", "final_semantics", "free_cleared"), params_type=VisibilityParams,
              run=run, code=("nuplan_occ.voxel",), doc=__doc__ or "")
