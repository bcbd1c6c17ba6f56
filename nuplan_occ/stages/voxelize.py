"""voxelize (a frame stage): per output frame, the background surface moved into the frame's ego frame (refined
pose) and each object's geometry placed by its corrected box at that frame (nuplan_occ.voxel.placement: a box
lattice for `box_fill_categories`, else its carved solid, else its surface, else its raw windowed points);
background inside current boxes is removed; surfaces are voxelized exactly (no holes where triangles exceed a
voxel) and objects filled inside their surface (nuplan_occ.voxel.compose). Gives instance ids (stable per
log) and per-voxel flow. With `unboxed_movers`, the frame's own points that the aggregate removed as dynamic
are painted into empty voxels as labeled clusters (nuplan_occ.voxel.movers), and the clusters of
`mover_gather_categories` gather the flagged points of the `mover_gather_frames` output frames before and after,
moved by their own motion, and are filled as the solid those outline, while those of `mover_trace_categories` gather
the `mover_trace_frames` around them and paint the gathered points as they are (nuplan_occ.voxel.mover_solids). Then the voxels of
`ground_contact_categories`, boxed or not, reach down to the ground under them (nuplan_occ.voxel.ground_contact).
With `clear_ego_box`, the voxels inside the ego vehicle's own box, above the ground layer, end empty
(nuplan_occ.voxel.compose.clear_ego_box).

Inputs: `scene`, `registration`, `object_boxes`, `background_surface`, `scene_frame`, `objects`,
`object_surfaces`, `object_solids`, `frame_movers`; prepared once per scene: `background_tiles` (the
background surface indexed on x-y tiles, so a frame's crop touches only the surface near it). Frame output:
`grids` (the frame's FrameGrids, ego frame; background labeled OTHER here), or `failure` for a sweep that
did not load.
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.io.types import PACIFICA
from nuplan_occ.labels import BOX_CATEGORIES, LABELS
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.voxel.compose import clear_ego_box, compose_frame
from nuplan_occ.voxel.ground_contact import reach_down_to_ground
from nuplan_occ.voxel.mover_gathering import GatherSettings
from nuplan_occ.voxel.mover_solids import gathered_solids, gathered_traces
from nuplan_occ.voxel.movers import mover_voxels, movers_around, neighbour_movers, paint_empty, recurring_points
from nuplan_occ.voxel.placement import placed_objects
from nuplan_occ.voxel.surface_tiles import build_surface_tiles


@dataclass(frozen=True)
class VoxelizeParams:
    fill_objects: bool = param(True, "fill closed object surfaces (vehicles are solid)")
    pedestrian_window: int = param(2, "sweeps on each side whose points shape a non-rigid object at a frame", low=0)
    crop_margin_m: float = param(1.0, "background surface kept beyond the grid", unit="m", low=0.0)
    box_fill_categories: tuple[str, ...] = param(("pedestrian",), "categories filled as their corrected box",
                                                 choices=BOX_CATEGORIES)
    box_fill_spacing_m: float = param(0.05, "spacing of the points that fill a box", unit="m", low=0.0,
                                      low_open=True)
    ground_layer_categories: tuple[str, ...] = param(("vehicle", "czone_sign"), "categories whose voxels in the "
                                                     "ground layer are ground", choices=BOX_CATEGORIES)
    ground_contact_categories: tuple[str, ...] = param(("vehicle",), "categories whose objects reach down to the "
                                                       "ground under them (a car's wheels and underside)",
                                                       choices=BOX_CATEGORIES)
    ground_contact_reach_m: float = param(0.5, "the tallest gap between an object and its ground that it fills (0: "
                                          "none)", unit="m", low=0.0)
    solid_min_cells: int = param(4, "solid cells a voxel must hold to take a sparse solid (or one observed cell)",
                                 low=1)
    sparse_solid_categories: tuple[str, ...] = param(("vehicle",), "categories whose carved solids need "
                                                     "solid_min_cells per voxel", choices=BOX_CATEGORIES)
    unboxed_movers: bool = param(True, "paint the frame's own points the aggregate removed as dynamic into empty "
                                 "voxels")
    mover_min_voxels: int = param(2, "mover clusters with fewer voxels are not painted", low=1)
    mover_vehicle_extent_m: float = param(2.5, "a mover cluster at least this long (x or y) is a vehicle", unit="m",
                                          low=0.0)
    mover_vehicle_max_height_m: float = param(4.5, "a mover cluster whose top stands higher above its ground is "
                                              "not a vehicle", unit="m", low=0.0)
    mover_bicycle_extent_m: float = param(1.0, "a shorter moving cluster at least this long is a bicycle", unit="m",
                                          low=0.0)
    mover_static_frames: int = param(5, "output frames before and after whose movers tell static structure",
                                     low=1)
    mover_static_fraction: float = param(0.2, "a cluster with at least this share of its points recurring there "
                                         "is not a bicycle", low=0.0, high=1.0)
    mover_ground_reach_m: float = param(0.75, "a cluster whose lowest voxel is higher above the ground is other",
                                        unit="m", low=0.0)
    mover_fragment_reach_m: float = param(1.0, "a shorter cluster within this gap of a vehicle cluster is a "
                                          "vehicle (0: none)", unit="m", low=0.0)
    mover_bicycle_min_height_m: float = param(1.5, "a moving cluster is a bicycle only when its top stands at least "
                                              "this high above its ground (a rider)", unit="m", low=0.0)
    mover_bicycle_max_width_m: float = param(1.5, "a moving cluster is a bicycle only when it spans at most this "
                                             "across its motion (read from the frames mover_static_frames before "
                                             "and after)", unit="m", low=0.0)
    mover_motion_reach_m: float = param(4.0, "radius around a mover cluster in which those frames' flagged points "
                                        "tell its motion", unit="m", low=0.0, low_open=True)
    mover_classes: tuple[str, ...] = param(("vehicle", "bicycle"), "classes the unboxed-mover rule may give; a cluster it "
                                           "would give another is other", choices=("vehicle", "bicycle"))
    mover_gather_categories: tuple[str, ...] = param(("vehicle",), "unboxed-mover classes that gather the frames "
                                                     "around them and are filled as solids",
                                                     choices=("vehicle", "bicycle"))
    mover_gather_frames: int = param(5, "output frames before and after that an unboxed mover gathers (0: none)",
                                     low=0)
    mover_gather_step_m: float = param(2.5, "the farthest an unboxed mover moves from one output frame to the "
                                       "next", unit="m", low=0.0, low_open=True)
    mover_gather_min_overlap: float = param(0.3, "share of the smaller occupancy that must overlay to gather a "
                                            "frame", low=0.0, high=1.0)
    mover_trace_categories: tuple[str, ...] = param(("bicycle",), "unboxed-mover classes that gather the flagged "
                                                    "points of the mover_trace_frames output frames before and after "
                                                    "and paint them as they are (no solid: a rider is no column)",
                                                    choices=("vehicle", "bicycle"))
    mover_trace_frames: int = param(1, "output frames before and after that such a mover gathers (0: none)", low=0)
    mover_trace_min_points: int = param(2, "a voxel such a mover paints holds at least this many of its gathered "
                                        "points", low=1)
    mover_solid_reach_m: float = param(0.5, "a gathered mover's column without points reaches up to the lowest top "
                                       "of the columns within this distance", unit="m", low=0.0)
    mover_bicycle_ground_fill_m: float = param(0.5, "a bicycle's columns whose lowest voxel is at most this high "
                                               "reach down to the ground (0: none)", unit="m", low=0.0)
    clear_ego_box: bool = param(True, "voxels inside the ego vehicle's box (nuPlan Pacifica) above the ground layer are "
                                "empty")


def prepare(inputs: dict, params: VoxelizeParams) -> dict:
    """Once per scene: the background surface indexed on x-y tiles of the scene frame (`background_tiles`)."""
    surface = inputs["background_surface"]
    return {"background_tiles": build_surface_tiles(surface.vertices, surface.faces)}


def run(inputs: dict, frame: dict, params: VoxelizeParams) -> dict:
    scene = inputs["scene"]
    position = frame["position"]
    sweep = scene.sweeps[position]
    if not sweep.has_cloud:
        return {"failure": sweep.failure or "frame was not built"}
    ok_position = scene.ok_indices().index(position)
    T_ego_from_global = invert_transform(inputs["registration"].poses[position])
    T_ego_from_scene = T_ego_from_global @ inputs["scene_frame"]
    vertices, faces = inputs["background_tiles"].crop(T_ego_from_scene, DEFAULT_GRID.lower - params.crop_margin_m,
                                                      DEFAULT_GRID.upper + params.crop_margin_m)
    objects = placed_objects(scene.instance_ids, inputs["object_boxes"][position], ok_position, inputs["objects"],
                             inputs["object_surfaces"], inputs["object_solids"], params.pedestrian_window,
                             params.box_fill_categories, params.box_fill_spacing_m,
                             params.sparse_solid_categories, params.solid_min_cells)
    grids = compose_frame(
        vertices, faces, objects, None, DEFAULT_GRID, fill_objects=params.fill_objects,
        ground_layer_classes=tuple(LABELS.box_category_to_id[c] for c in params.ground_layer_categories))
    if params.unboxed_movers:
        points = inputs["frame_movers"][position]
        others = neighbour_movers(inputs["frame_movers"], position, params.mover_static_frames)
        points_ego = transform_points(T_ego_from_scene, points)
        movers = mover_voxels(points_ego, DEFAULT_GRID, params.mover_min_voxels,
                              params.mover_vehicle_extent_m, bicycle_extent_m=params.mover_bicycle_extent_m,
                              recurring=recurring_points(points, others, DEFAULT_GRID.voxel_size) if others else None,
                              static_fraction=params.mover_static_fraction, ground_height=grids.ground_height,
                              ground_reach_m=params.mover_ground_reach_m,
                              fragment_reach_m=params.mover_fragment_reach_m,
                              bicycle_ground_fill_m=params.mover_bicycle_ground_fill_m,
                              classes=tuple(LABELS.box_category_to_id[c] for c in params.mover_classes),
                              bicycle_min_height_m=params.mover_bicycle_min_height_m,
                              neighbours=tuple(transform_points(T_ego_from_scene, o) for o in others) if others else None,
                              bicycle_max_width_m=params.mover_bicycle_max_width_m,
                              motion_reach_m=params.mover_motion_reach_m,
                              vehicle_max_height_m=params.mover_vehicle_max_height_m)
        grids.mover_voxels = paint_empty(grids, movers)
        if params.mover_gather_categories:
            around = {step: transform_points(T_ego_from_scene, p) for step, p in
                      movers_around(inputs["frame_movers"], position, params.mover_gather_frames).items()}
            solids = gathered_solids(
                movers, points_ego, around, grids.ground_height,
                tuple(LABELS.box_category_to_id[c] for c in params.mover_gather_categories),
                GatherSettings(step_m=params.mover_gather_step_m, min_overlap=params.mover_gather_min_overlap),
                params.mover_solid_reach_m, DEFAULT_GRID)
            grids.mover_voxels += paint_empty(grids, solids)
        if params.mover_trace_categories and params.mover_trace_frames:
            around = {step: transform_points(T_ego_from_scene, p) for step, p in
                      movers_around(inputs["frame_movers"], position, params.mover_trace_frames).items()}
            traces = gathered_traces(
                movers, points_ego, around, tuple(LABELS.box_category_to_id[c] for c in params.mover_trace_categories),
                GatherSettings(step_m=params.mover_gather_step_m, min_overlap=params.mover_gather_min_overlap),
                params.mover_trace_min_points, DEFAULT_GRID)
            grids.mover_voxels += paint_empty(grids, traces)
    reach_down_to_ground(grids, tuple(LABELS.box_category_to_id[c] for c in params.ground_contact_categories),
                         params.ground_contact_reach_m)
    if params.clear_ego_box:
        grids.ego_cleared = clear_ego_box(grids, *PACIFICA.box_center_and_size())
    return {"grids": grids}


STAGE = Stage("voxelize",
              inputs=("scene", "registration", "object_boxes", "background_surface", "scene_frame", "objects",
                      "object_surfaces", "object_solids", "frame_movers"),
              outputs=("grids",), params_type=VoxelizeParams, run=run, per_frame=True, prepare=prepare)
