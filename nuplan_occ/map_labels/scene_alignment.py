"""A scene's map alignment: the correction that moves the scene's bright flat-ground LiDAR returns (road
paint) onto the map's painted lines, and the stop-line edges whose strips those returns show painted.

`scene` is a nuplan_occ.pipeline.scene.SceneData; poses are its sweeps' refined T_global_from_ego (F, 4, 4);
layers are the map's label layers (nuplan_occ.io.maps) in the global frame.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.map_labels.bev import STOP_LINE_LAYERS, map_geometries, painted_lines
from nuplan_occ.map_labels.map_align import (MapAlignment, align_points_to_lines, ground_returns, paint_confirmed,
                                             polygon_edges)


def align_scene_to_map(scene, poses: np.ndarray, layers: dict, positions: list[int], paint_intensity_ratio: float,
                       max_offset_m: float, max_yaw_deg: float, confirm_stop_lines: bool, line_width_m: float
                       ) -> tuple[MapAlignment, np.ndarray | None]:
    """(the scene's map correction, the stop-line edges to paint). The returns of the sweeps at `positions`
    at least paint_intensity_ratio times brighter than the ground at the same range are aligned to the painted
    lines (a correction moving the scene more than max_offset_m or turning it more than max_yaw_deg is
    refused); with confirm_stop_lines, the stop polygons' edges whose strip (line_width_m wide) the corrected
    returns show painted are returned (an (E, 2, 2) array of edges), else None (paint whole outlines)."""
    returns = ground_returns(scene.clouds_of(positions), poses[positions], scene.sensor_origin_ego,
                             ratio=paint_intensity_ratio)
    alignment = align_points_to_lines(returns.xy[returns.bright], painted_lines(layers),
                                      max_offset_m=max_offset_m, max_yaw_deg=max_yaw_deg)
    if not confirm_stop_lines:
        return alignment, None
    edges = polygon_edges(map_geometries(layers, STOP_LINE_LAYERS))
    return alignment, edges[paint_confirmed(edges, returns.moved(alignment.correction), line_width_m)]


def map_window(poses: np.ndarray, positions: list[int], margin_m: float) -> tuple[np.ndarray, float]:
    """(centre (2,), half size m) of the square window of the map around the x, y positions of the sweeps at
    `positions`, grown by margin_m."""
    centers = poses[positions][:, :2, 3]
    middle = (centers.min(axis=0) + centers.max(axis=0)) / 2.0
    return middle, float(np.max(centers.max(axis=0) - centers.min(axis=0))) / 2.0 + margin_m
