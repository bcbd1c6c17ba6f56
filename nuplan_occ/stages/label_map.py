"""label_map (params: the `label` section, declared by the label stage): read the map's label layers around
the scene and align them to the LiDAR's road paint: a 2D rigid correction that moves the scene's bright
ground returns onto the map's painted lines (nuplan_occ.map_labels.scene_alignment), and the stop-polygon
edges whose strips the returns show painted. Without a map for the log, the label stage leaves background
`other` and every frame records why.

Inputs: `scene`, `registration`. Outputs: `map_layers` (the map's label layers around the scene, global
frame; None without a map), `map_status` (str: "" when the map was used, else why not), `map_alignment`
(MapAlignment or None), `stop_lines` (stop polygon edges to paint; None: whole outlines).
"""

from __future__ import annotations

from typing import Any

from nuplan_occ.io.maps import LABEL_LAYERS, NuplanMap
from nuplan_occ.map_labels.scene_alignment import align_scene_to_map, map_window
from nuplan_occ.pipeline.stage import Stage

MAP_MARGIN_M = 75.0
"""The map is read this far beyond the scene's output frames' positions (a grid reaches 70.7 m from its ego)."""


def run(inputs: dict, params: Any) -> dict:
    scene = inputs["scene"]
    poses = inputs["registration"].poses
    built = [i for i in scene.ok_indices() if scene.sweeps[i].is_output]
    layers, map_status, alignment, stop_lines = None, scene.map_problem or "no map file found for the log's map", None, None
    if scene.map_path is not None and built:
        middle, half_size = map_window(poses, built, MAP_MARGIN_M)
        layers = NuplanMap(scene.map_path).layers_in_window(middle, half_size, LABEL_LAYERS)
        map_status = ""
        if params.align_to_paint:
            alignment, stop_lines = align_scene_to_map(
                scene, poses, layers, scene.spread_positions(params.align_sweep_stride, params.align_max_sweeps),
                params.paint_intensity_ratio, params.align_max_offset_m, params.align_max_yaw_deg,
                params.confirm_stop_lines, params.line_width_m)
    return {"map_layers": layers, "map_status": map_status, "map_alignment": alignment, "stop_lines": stop_lines}


STAGE = Stage("label_map", inputs=("scene", "registration"),
              outputs=("map_layers", "map_status", "map_alignment", "stop_lines"), params_type=None,
              params_section="label", run=run)
