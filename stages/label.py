"""Stage 8, label: background voxels of the ground layer (within a tolerance of the locally estimated
ground height) take the BEV map class at that column — drivable -> road, painted lines -> road_line,
other ground -> other_ground; background above the ground layer stays `other`; objects keep their
box class. The BEV map is rasterized from the GPKG vector layers in each frame's (refined) ego frame.
Without a map for the log, background stays `other` and the frame records why.

Inputs: `scene`, `registration`, `grids`. Outputs: `semantics` (sweep token -> uint8 grid),
`map_status` (str: "" when the map was used).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.io.maps import LABEL_LAYERS, NuplanMap
from nuplan_occ.labels import OTHER
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.voxel.bev import rasterize_bev
from nuplan_occ.voxel.ground import label_background


@dataclass(frozen=True)
class LabelParams:
    """ground_tolerance_m: height above the local ground still counted as ground layer;
    line_width_m: painted width of lane/road boundaries and stop lines."""

    ground_tolerance_m: float = 0.3
    line_width_m: float = 0.15


def run(inputs: dict, params: LabelParams) -> dict:
    scene = inputs["scene"]
    poses = inputs["registration"].poses
    grids = inputs["grids"]
    position_of = {sweep.token: i for i, sweep in enumerate(scene.sweeps)}
    layers, map_status = None, "no map file found for the log's map"
    if scene.map_path is not None and grids:
        centers = np.stack([poses[position_of[token]][:2, 3] for token in grids])
        middle = (centers.min(axis=0) + centers.max(axis=0)) / 2.0
        half_size = float(np.max(centers.max(axis=0) - centers.min(axis=0))) / 2.0 + 75.0
        layers = NuplanMap(scene.map_path).layers_in_window(middle, half_size, LABEL_LAYERS)
        map_status = ""
    semantics = {}
    for token, grid in grids.items():
        labeled = grid.semantics.copy()
        if layers is not None:
            bev = rasterize_bev(layers, poses[position_of[token]], DEFAULT_GRID, line_width_m=params.line_width_m)
            background = label_background(grid.occupied_background, bev, DEFAULT_GRID,
                                          ground_tolerance_m=params.ground_tolerance_m)
            replace = grid.occupied_background & (labeled == OTHER)
            labeled[replace] = background[replace]
        semantics[token] = labeled
    return {"semantics": semantics, "map_status": map_status}


STAGE = Stage("label", inputs=("scene", "registration", "grids"), outputs=("semantics", "map_status"),
              params_type=LabelParams, run=run, code=("nuplan_occ.voxel", "nuplan_occ.io.maps"), doc=__doc__ or "")
