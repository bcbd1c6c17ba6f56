"""visibility (a frame stage): `mask_lidar` from the frame's own LiDAR rays (voxels traversed = observed free,
the return's voxel = observed occupied, the rest unknown); free-space consistency: background voxels those
rays crossed, holding no aggregated point and above the ground, are cleared, and so are voxels of the
`clear_object_categories` that the frame's own rays crossed without touching the objects' own points, and
voxels of boxed objects of the `clear_far_object_categories` that those rays crossed in columns far from every
object point (nuplan_occ.rays.free_space); then `mask_camera` from the cameras' frusta with occlusion by the frame's
cleared occupancy. It declares the `visibility` params section, which the lidar_rays and support stages read
too.

Inputs: `scene`, `registration`, `observations`, `observation_bits`, `background_support` (each row's voxels
holding aggregated background points), frame inputs `grids`, `semantics`. Prepared once per scene:
`camera_segments` (the cameras' rays) and, with free_space_other_frames, `free_bits` (every row's FREE bits,
so a frame can use the other frames' free space without holding their grids). Frame outputs: `masks`
({"mask_lidar", "mask_camera"} bool grids), `final_semantics` (`semantics` with the cleared voxels empty),
`free_cleared` (number of voxels cleared, background and objects).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import BOX_CATEGORIES, LABELS
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.rays.free_space import crossed_far_from_points, crossed_objects
from nuplan_occ.rays.observations import frames_to, free_space_clear, split_observation_bits
from nuplan_occ.rays.visibility import camera_segments, visible_along


@dataclass(frozen=True)
class VisibilityParams:
    lidar: bool = param(True, "cast the LiDAR rays: mask_lidar, free-space clearing, the aggregate's dynamic test")
    camera: bool = param(True, "make mask_camera from the log's cameras")
    camera_max_range_m: float = param(60.0, "farthest distance a camera is taken to observe", unit="m",
                                      low=0.0, low_open=True)
    camera_range_bands: int = param(3, "range bands of the camera rays' lattices (1: one lattice fine enough for the "
                                    "largest range everywhere)", low=1)
    clear_free_space: bool = param(True, "clear background voxels that LiDAR rays show empty (needs lidar)")
    free_space_ground_margin_m: float = param(0.2, "only voxels whose centre is this far above the local ground "
                                              "are cleared", unit="m", low=0.0)
    free_space_other_frames: bool = param(True, "use the rays of the scene's other output frames too (the "
                                          "background is static)")
    clear_object_categories: tuple[str, ...] = param(
        ("pedestrian", "czone_sign"), "object categories whose voxels the frame's own rays crossed, holding none "
        "of the objects' points, are cleared (needs lidar)", choices=BOX_CATEGORIES)
    clear_far_object_categories: tuple[str, ...] = param(
        ("vehicle",), "boxed object categories whose voxels the frame's own rays crossed are cleared where no object "
        "point lies within clear_far_object_reach_m of their column (needs lidar)", choices=BOX_CATEGORIES)
    clear_far_object_reach_m: float = param(0.5, "x-y distance from the nearest column holding an object point "
                                            "beyond which crossed object voxels are cleared", unit="m", low=0.0)


def prepare(inputs: dict, params: VisibilityParams) -> dict:
    """Once per scene: the rays of the scene's cameras (`camera_segments`; None without camera masks) and
    every output frame's FREE bits (`free_bits` (F, n_bytes); None unless free_space_other_frames)."""
    scene = inputs["scene"]
    free_bits = None
    if params.lidar and params.clear_free_space and params.free_space_other_frames:
        free_bits = np.empty((len(inputs["observations"].tokens), (int(np.prod(DEFAULT_GRID.shape)) + 7) // 8), np.uint8)
        for row in range(len(free_bits)):  # one element read back at a time
            free_bits[row] = split_observation_bits(inputs["observation_bits"][row])[1]
    use = params.camera and bool(scene.cameras)
    return {"camera_segments": camera_segments(scene.cameras, DEFAULT_GRID, params.camera_max_range_m,
                                                range_bands=params.camera_range_bands) if use else None,
            "free_bits": free_bits}


def run(inputs: dict, frame: dict, params: VisibilityParams) -> dict:
    scene = inputs["scene"]
    position = frame["position"]
    token = scene.sweeps[position].token
    semantics = frame["semantics"].copy()
    grids = frame["grids"]
    masks, cleared = {}, 0
    if params.lidar:
        observations = inputs["observations"]
        row = observations.row(token)
        own_observed, own_free = split_observation_bits(inputs["observation_bits"][row])
        observed = np.unpackbits(own_observed, count=int(np.prod(DEFAULT_GRID.shape)))
        masks["mask_lidar"] = observed.reshape(DEFAULT_GRID.shape).astype(bool)
        if params.clear_free_space:
            support = np.unpackbits(inputs["background_support"][row], count=int(np.prod(DEFAULT_GRID.shape)))
            other_frames = None
            if params.free_space_other_frames:
                position_of = {sweep.token: i for i, sweep in enumerate(scene.sweeps)}
                other_frames = (inputs["free_bits"], frames_to(inputs["registration"].poses, position,
                                                               observations.tokens, position_of, row))
            clear = free_space_clear(grids.occupied_background & (semantics > 0),
                                     support.view(bool).reshape(DEFAULT_GRID.shape), grids.ground_height,
                                     DEFAULT_GRID, params.free_space_ground_margin_m, own_free, other_frames)
            semantics[clear] = 0
            cleared = int(np.count_nonzero(clear))
        if params.clear_object_categories:
            classes = tuple(LABELS.box_category_to_id[c] for c in params.clear_object_categories)
            crossed = crossed_objects(semantics, classes, grids.object_points, own_free, DEFAULT_GRID)
            semantics[crossed] = 0
            cleared += int(np.count_nonzero(crossed))
        if params.clear_far_object_categories:
            classes = tuple(LABELS.box_category_to_id[c] for c in params.clear_far_object_categories)
            boxed = np.isin(semantics, np.asarray(classes, np.uint8)) & (grids.instance > 0)
            far = crossed_far_from_points(boxed, grids.object_points, own_free, params.clear_far_object_reach_m,
                                          DEFAULT_GRID)
            semantics[far] = 0
            cleared += int(np.count_nonzero(far))
    if inputs["camera_segments"] is not None:
        masks["mask_camera"] = visible_along(semantics > 0, inputs["camera_segments"], DEFAULT_GRID)
    return {"masks": masks, "final_semantics": semantics, "free_cleared": cleared}


STAGE = Stage("visibility", inputs=("scene", "registration", "observations", "observation_bits", "background_support",
                                    "grids", "semantics"),
              outputs=("masks", "final_semantics", "free_cleared"), params_type=VisibilityParams,
              run=run, per_frame=True, prepare=prepare)
