"""support (params: the `visibility` section, declared by the visibility stage): for the visibility stage's free-space test: for each
output frame with LiDAR observations, the voxels of its grid that hold at least one point of the background
aggregate (nuplan_occ.rays.free_space.sorted_point_support), as packed bits. Made once per scene, before the
frame stream, so the stream reads one frame's bits at a time instead of holding the whole aggregate, whose
size grows with the scene's length.

Inputs: `scene`, `registration`, `background_aggregate` (points in ascending scene x), `observations`.
Output: `background_support`: an item output, one element per row of `observations` (the same frames, in the
same order): the frame's support grid, flat C order, packed as np.packbits packs it (640 KB); no elements
unless `lidar` and `clear_free_space`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.rays.free_space import sorted_point_support


def run(inputs: dict, params: Any) -> dict:
    scene, background = inputs["scene"], inputs["background_aggregate"]
    tokens = inputs["observations"].tokens if params.lidar and params.clear_free_space else []
    if tokens and np.any(np.diff(background.points[:, 0]) < 0):
        raise ValueError("support: the background aggregate's points are not in ascending scene x")
    position_of = {sweep.token: position for position, sweep in enumerate(scene.sweeps)}
    T_scene_from_global = invert_transform(background.T_global_from_scene)
    poses = inputs["registration"].poses

    def support_bits():  # one frame at a time, while the cache stores them
        for token in tokens:
            support = sorted_point_support(background.points, T_scene_from_global @ poses[position_of[token]], DEFAULT_GRID)
            yield np.packbits(support.ravel())

    return {"background_support": support_bits()}


STAGE = Stage("support", inputs=("scene", "registration", "background_aggregate", "observations"),
              outputs=("background_support",), item_outputs=("background_support",), params_type=None,
              params_section="visibility", run=run)
