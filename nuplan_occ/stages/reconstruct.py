"""reconstruct: surfaces from the aggregates with the neural-kernel-style torch solver ("nksr"), Open3D screened
Poisson ("poisson") or none (the raw points), and solid shapes of rigid objects.

The background is reconstructed in the scene frame, and a meshed background gets the ground height field of
its aggregate added where the LiDAR rings leave gaps (nuplan_occ.aggregation.ground_fill). Each rigid object
with at least `min_object_points` points is reconstructed in its box frame; the others (and non-rigid
objects, pedestrians, whose shape changes from frame to frame) are voxelized from their raw points. With
`carve_objects`, each rigid object of `carve_categories` with points also gets its solid by space carving of
its box (nuplan_occ.aggregation.carve: the box minus the space crossed by its own rays and by the background
rays through its box that the aggregate stage kept for it), which the voxelize stage prefers to its surface.

Inputs: `background_aggregate`, `objects`, `object_through_rays`.
Outputs: `background_surface` (Surface, scene frame), `scene_frame` (T_global_from_scene (4, 4) of that scene
frame, the aggregate's), `object_surfaces` (track -> Surface, box frame), `object_solids` (track ->
SolidSamples: points sampling the solid lattice cells, box frame, m: their centres, or their corners for
`corner_categories`; and which samples' cells hold an observed point).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.aggregation.carve import TopEnvelope, object_solid_samples
from nuplan_occ.aggregation.ground_fill import ground_fill_mesh
from nuplan_occ.labels import BOX_CATEGORIES
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.recon import METHODS, ReconParams, reconstruct


@dataclass(frozen=True)
class ReconstructParams:
    method: str = param("nksr", "surface method of the background", choices=METHODS)
    object_method: str = param("nksr", "surface method of the rigid objects", choices=METHODS)
    background_coarse_first: bool = param(True, "the background's solve fits its coarsest level first, the finer "
                                          "levels to what it leaves")
    min_object_points: int = param(200, "rigid objects with fewer points get no surface", low=0)
    mask_distance_m: float = param(0.2, "trim the background surface where it is farther than this from every "
                                   "aggregated point", unit="m", low=0.0, low_open=True)
    object_mask_distance_m: float = param(0.2, "trim an object's surface where it is farther than this from every "
                                          "one of its points", unit="m", low=0.0, low_open=True)
    ground_fill: bool = param(True, "add the aggregate's ground height field to a meshed background")
    ground_fill_max_edge_m: float = param(10.0, "longest triangle edge of the ground fill", unit="m", low=0.0,
                                          low_open=True)
    carve_objects: bool = param(True, "give the rigid objects of carve_categories a solid by space carving")
    carve_categories: tuple[str, ...] = param(("vehicle", "barrier", "czone_sign", "generic_object"),
                                              "categories whose objects are carved", choices=BOX_CATEGORIES)
    carve_resolution_m: float = param(0.1, "edge of the carving lattice's cells", unit="m", low=0.0, low_open=True)
    min_carve_points: int = param(1, "objects with fewer points are not carved", low=1)
    corner_categories: tuple[str, ...] = param(("barrier", "generic_object"), "categories whose solids are sampled "
                                               "at every cell's corners instead of its centre", choices=BOX_CATEGORIES)
    envelope_categories: tuple[str, ...] = param(("vehicle",), "carved categories whose solids end at the top of "
                                                 "their points (no overhang: the unseen air above a truck's bed is "
                                                 "not solid)", choices=BOX_CATEGORIES)
    envelope_reach_m: float = param(0.1, "a solid cell keeps the highest point of the columns this near", unit="m",
                                    low=0.0)
    envelope_pad_m: float = param(0.0, "a solid cell may start this far above that point", unit="m", low=0.0)
    envelope_floor_m: float = param(0.3, "points this close above the box's bottom are ground, no top", unit="m",
                                    low=0.0)
    envelope_across_width: bool = param(True, "a column with no point near takes the highest point across the box's "
                                        "width at its place along the length")
    envelope_unseen_quantile: float = param(0.1, "a column with no point near nor across the width takes this "
                                            "quantile of the seen columns' highest points (an unseen end is a "
                                            "bonnet or a bed, not a cabin)", low=0.0, high=1.0)
    envelope_side_quantile: float = param(0.999, "a solid of envelope_categories ends at this quantile of its body "
                                          "points' reach along and across its box, symmetric about the centre (the box's "
                                          "room around the object is not solid; 1: the farthest point)", low=0.0,
                                          high=1.0)


def run(inputs: dict, params: ReconstructParams) -> dict:
    background = inputs["background_aggregate"]
    background_surface = reconstruct(background.points, background.frame_origins, method=params.method,
                                     params=ReconParams(mask_distance=params.mask_distance_m,
                                                        coarse_first=params.background_coarse_first), frame="scene",
                                     origin_ids=background.frame_ids)
    if params.ground_fill and len(background_surface.faces):
        vertices, faces = ground_fill_mesh(background.points, max_edge_m=params.ground_fill_max_edge_m)
        background_surface = background_surface.with_triangles(vertices, faces, ground_fill_faces=len(faces))
    object_surfaces, object_solids = {}, {}
    envelope = TopEnvelope(params.envelope_reach_m, params.envelope_pad_m, params.envelope_floor_m,
                           params.envelope_across_width, params.envelope_unseen_quantile, params.envelope_side_quantile)
    for track, aggregate in inputs["objects"].items():
        if not aggregate.rigid:
            continue
        carve = params.carve_objects and aggregate.category in params.carve_categories
        if carve and len(aggregate.points) >= params.min_carve_points:
            object_solids[track] = object_solid_samples(aggregate.points, aggregate.sensor_origins, aggregate.size,
                                                        params.carve_resolution_m,
                                                        inputs["object_through_rays"].get(track),
                                                        corners=aggregate.category in params.corner_categories,
                                                        envelope=envelope if aggregate.category in
                                                        params.envelope_categories else None)
        if len(aggregate.points) >= params.min_object_points:
            object_surfaces[track] = reconstruct(aggregate.points, aggregate.sensor_origins,
                                                 method=params.object_method, frame="box",
                                                 params=ReconParams(mask_distance=params.object_mask_distance_m))
    return {"background_surface": background_surface, "scene_frame": background.T_global_from_scene,
            "object_surfaces": object_surfaces, "object_solids": object_solids}


STAGE = Stage("reconstruct", inputs=("background_aggregate", "objects", "object_through_rays"),
              outputs=("background_surface", "scene_frame", "object_surfaces", "object_solids"),
              params_type=ReconstructParams, run=run, kept=True)
