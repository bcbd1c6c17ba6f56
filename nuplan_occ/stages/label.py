"""Stage 8, label (a scene step, then a frame stage): background voxels of the ground layer (within a
tolerance of the ground height voxelize estimated for the frame, `FrameGrids.ground_height`: the ground its
box removal kept) take the BEV map class at that column — drivable -> road, painted lines -> road_line,
other ground -> other_ground; background above the ground layer stays `other`; objects keep their
box class. The BEV map is rasterized from the GPKG vector layers in each frame's (refined) ego frame,
corrected by the scene's map alignment: a 2D rigid transform that moves the scene's bright ground returns
(paint) onto the map's painted lines (nuplan_occ.map_labels.map_align). Without a map for the log, background
stays `other` and the frame records why.

Scene step `label_map` (params section `label`): inputs `scene`, `registration`; outputs `map_layers` (the
map's label layers around the scene, None without a map), `map_status` (str: "" when the map was used),
`map_alignment` (MapAlignment or None), `stop_lines` (stop polygon edges to paint, None: whole outlines).
Frame stage `label`: frame input `grids`; frame output `semantics` (uint8 grid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.io.maps import LABEL_LAYERS, NuplanMap
from nuplan_occ.labels import OTHER
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.map_labels.bev import STOP_LINE_LAYERS, map_geometries, painted_lines, rasterize_bev
from nuplan_occ.voxel.ground import label_background
from nuplan_occ.map_labels.map_align import (MapAlignment, align_points_to_lines, ground_returns, paint_confirmed,
                                         polygon_edges)


@dataclass(frozen=True)
class LabelParams:
    """ground_tolerance_m: height above the local ground still counted as ground layer;
    line_width_m: painted width of lane/road boundaries and stop lines.
    align_to_paint: correct the scene's poses against the map before rasterizing it (see
    nuplan_occ.map_labels.map_align): ground returns at least paint_intensity_ratio times brighter than the ground
    at the same range, from every align_sweep_stride-th sweep (at most align_max_sweeps of them, spread evenly over
    the scene: `SceneData.spread_positions`; 0 = all), are aligned to the painted lines; a
    correction moving the scene more than align_max_offset_m or turning it more than align_max_yaw_deg is
    refused (recorded, map used as is). align_max_sweeps: a longer scene sees the same paint again from a little
    further along, so a bounded number of sweeps spread over it aligns as well (bench/report-scale.md's notes).
    confirm_stop_lines (with align_to_paint): a stop polygon's edge is painted as road_line only where the
    flat-ground returns in its strip are mostly bright (nuplan_occ.map_labels.map_align.paint_confirmed). The
    map gives stop polygons, not which edge carries the paint (nuPlan's format leaves that open); painting
    whole outlines marked unpainted asphalt as road_line (bench: road_line IoU 0.75 -> 0.83 with the check)."""

    ground_tolerance_m: float = 0.3
    line_width_m: float = 0.15
    align_to_paint: bool = True
    paint_intensity_ratio: float = 3.0
    align_sweep_stride: int = 2
    align_max_sweeps: int = 50
    align_max_offset_m: float = 0.5
    align_max_yaw_deg: float = 1.0
    confirm_stop_lines: bool = True


def align_map(scene, poses: np.ndarray, layers: dict, params: LabelParams) -> tuple[MapAlignment, np.ndarray | None]:
    """The scene's map correction (bright flat-ground returns of the `spread_positions` of the loaded sweeps,
    refined poses, against the map's painted lines) and the stop lines to paint: the stop polygon edges
    whose strip the corrected returns show painted (None: paint whole outlines, without confirmation)."""
    used = scene.spread_positions(params.align_sweep_stride, params.align_max_sweeps)
    returns = ground_returns(scene.clouds_of(used), poses[used], scene.sensor_origin_ego,
                             ratio=params.paint_intensity_ratio)
    alignment = align_points_to_lines(returns.xy[returns.bright], painted_lines(layers),
                                      max_offset_m=params.align_max_offset_m, max_yaw_deg=params.align_max_yaw_deg)
    if not params.confirm_stop_lines:
        return alignment, None
    edges = polygon_edges(map_geometries(layers, STOP_LINE_LAYERS))
    return alignment, edges[paint_confirmed(edges, returns.moved(alignment.correction), params.line_width_m)]


def run_map(inputs: dict, params: LabelParams) -> dict:
    scene = inputs["scene"]
    poses = inputs["registration"].poses
    built = [i for i in scene.ok_indices() if scene.sweeps[i].is_output]
    layers, map_status, alignment, stop_lines = None, "no map file found for the log's map", None, None
    if scene.map_path is not None and built:
        centers = poses[built][:, :2, 3]
        middle = (centers.min(axis=0) + centers.max(axis=0)) / 2.0
        half_size = float(np.max(centers.max(axis=0) - centers.min(axis=0))) / 2.0 + 75.0
        layers = NuplanMap(scene.map_path).layers_in_window(middle, half_size, LABEL_LAYERS)
        map_status = ""
        if params.align_to_paint:
            alignment, stop_lines = align_map(scene, poses, layers, params)
    return {"map_layers": layers, "map_status": map_status, "map_alignment": alignment, "stop_lines": stop_lines}


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


MAP_STAGE = Stage("label_map", inputs=("scene", "registration"),
                  outputs=("map_layers", "map_status", "map_alignment", "stop_lines"), params_type=LabelParams,
                  run=run_map, code=("nuplan_occ.voxel", "nuplan_occ.io.maps"), doc=__doc__ or "",
                  params_section="label")

STAGE = Stage("label", inputs=("scene", "registration", "map_layers", "map_alignment", "stop_lines", "grids"),
              outputs=("semantics",), params_type=LabelParams, run=run, code=("nuplan_occ.voxel",), doc=__doc__ or "",
              per_frame=True)
