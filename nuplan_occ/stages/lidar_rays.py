"""lidar_rays (params: the `visibility` section, declared by the visibility stage): cast each loaded output frame's own LiDAR rays through its grid
once per scene (nuplan_occ.rays.visibility.lidar_observation_bits): the voxels each ray traverses are observed
free, the return's voxel observed occupied. Rays start at the merged LiDAR frame's origin, the only sensor
pose nuPlan stores.

Inputs: `scene`. Outputs: `observations` (RayObservations: the sweep tokens of the loaded output frames, one
row each; none without `visibility.lidar`) and `observation_bits` (an item output, one element per row: the
frame's observed grid and FREE grid as packed bits, 640 KB, read back one frame at a time by later stages).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.rays.observations import RayObservations
from nuplan_occ.rays.visibility import lidar_observation_bits


def run(inputs: dict, params: Any) -> dict:
    scene = inputs["scene"]
    positions = [p for p in scene.output_positions() if scene.sweeps[p].has_cloud] if params.lidar else []

    def observation_bits():  # one frame at a time, while the cache stores them
        for position in positions:
            yield np.concatenate(lidar_observation_bits(scene.sweeps[position].xyz, scene.sensor_origin_ego, DEFAULT_GRID))

    return {"observations": RayObservations([scene.sweeps[p].token for p in positions]),
            "observation_bits": observation_bits()}


STAGE = Stage("lidar_rays", inputs=("scene",), outputs=("observations", "observation_bits"),
              item_outputs=("observation_bits",), params_type=None, params_section="visibility", run=run)
