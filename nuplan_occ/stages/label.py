"""label (a frame stage): background voxels of the ground layer (within `ground_tolerance_m` of the ground
height voxelize estimated for the frame, `FrameGrids.ground_height`) take the BEV map class of their column:
drivable -> road, painted lines -> road_line, other ground -> other_ground; background above the ground layer
stays `other`; objects keep their box class. The BEV map is rasterized from the map's layers in the frame's
refined ego frame, corrected by the scene's map alignment (label_map stage). It declares the `label` params
section, which the label_map stage reads too.

Inputs: `scene`, `registration`, `map_layers`, `map_alignment`, `stop_lines`, frame input `grids`.
Frame output: `semantics` (uint8 grid [x, y, z], label ids).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import OTHER
from nuplan_occ.map_labels.bev import rasterize_bev
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.voxel.ground import label_background


@dataclass(frozen=True)
class LabelParams:
    ground_tolerance_m: float = param(0.3, "height above the local ground still counted as ground layer", unit="m",
                                      low=0.0)
    line_width_m: float = param(0.15, "painted width of lane / road boundaries and stop lines", unit="m",
                                low=0.0, low_open=True)
    align_to_paint: bool = param(True, "correct the scene's poses against the map's painted lines before "
                                 "rasterizing it")
    paint_intensity_ratio: float = param(3.0, "paint returns are at least this many times brighter than the ground "
                                         "at the same range", low=1.0)
    align_sweep_stride: int = param(2, "paint is taken from every n-th loaded sweep", low=1)
    align_max_sweeps: int = param(50, "at most this many of them, spread over the scene (0: all)", low=0)
    align_max_offset_m: float = param(0.5, "a correction moving the scene farther is refused", unit="m", low=0.0)
    align_max_yaw_deg: float = param(1.0, "a correction turning the scene more is refused", unit="deg",
                                     low=0.0, high=180.0)
    confirm_stop_lines: bool = param(True, "paint a stop polygon's edge as road_line only where the returns in its "
                                     "strip are mostly bright (needs align_to_paint)")


def run(inputs: dict, frame: dict, params: LabelParams) -> dict:
    grid, layers, alignment = frame["grids"], inputs["map_layers"], inputs["map_alignment"]
    labeled = grid.semantics.copy()
    if layers is not None:
        correction = alignment.correction if alignment is not None else np.eye(4)
        bev = rasterize_bev(layers, correction @ inputs["registration"].poses[frame["position"]], DEFAULT_GRID,
                            line_width_m=params.line_width_m, stop_lines=inputs["stop_lines"])
        background = label_background(grid.occupied_background, bev, DEFAULT_GRID,
                                      ground_tolerance_m=params.ground_tolerance_m, ground_height=grid.ground_height)
        np.copyto(labeled, background, where=grid.occupied_background & (labeled == OTHER))
    return {"semantics": labeled}


STAGE = Stage("label", inputs=("scene", "registration", "map_layers", "map_alignment", "stop_lines", "grids"),
              outputs=("semantics",), params_type=LabelParams, run=run, per_frame=True)
