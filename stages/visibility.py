"""Stage 9, visibility: `mask_lidar` by casting the frame's own LiDAR rays through the grid (voxels
traversed = observed free, the return voxel = observed occupied, the rest unknown), and `mask_camera`
from the 8 cameras' frusta with occlusion by the frame's occupancy.

Rays start at the merged LiDAR frame's origin (the only sensor pose nuPlan stores).
Inputs: `scene`, `semantics`. Outputs: `masks` (sweep token -> {"mask_lidar", "mask_camera"}).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.voxel.visibility import camera_visibility, lidar_visibility


@dataclass(frozen=True)
class VisibilityParams:
    """camera_max_range_m: farthest distance a camera is taken to observe."""

    lidar: bool = True
    camera: bool = True
    camera_max_range_m: float = 60.0


def run(inputs: dict, params: VisibilityParams) -> dict:
    scene = inputs["scene"]
    masks = {}
    for sweep in scene.sweeps:
        if sweep.token not in inputs["semantics"]:
            continue
        semantics = inputs["semantics"][sweep.token]
        masks[sweep.token] = {}
        if params.lidar:
            masks[sweep.token]["mask_lidar"] = lidar_visibility(sweep.cloud.xyz, scene.sensor_origin_ego, DEFAULT_GRID)
        if params.camera and scene.cameras:
            masks[sweep.token]["mask_camera"] = camera_visibility(
                semantics > 0, scene.cameras, DEFAULT_GRID, max_range_m=params.camera_max_range_m)
    return {"masks": masks}


STAGE = Stage("visibility", inputs=("scene", "semantics"), outputs=("masks",), params_type=VisibilityParams,
              run=run, code=("nuplan_occ.voxel",), doc=__doc__ or "")
