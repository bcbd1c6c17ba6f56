"""aggregate: the scene's background in one scene frame, placed by the refined poses, and each track's points
in its box frame, accumulated over the scene.

Background: each sweep's background within `max_range_m` of its ego, without the points near its objects'
corrected boxes (`object_clearance_m`), cropped to the output frames' grids plus `crop_margin_m` and thinned
to one point per `voxel_downsample_m` cube; the outlier test the filter stage left to the aggregate (long
scenes) runs on it, points under the cloud's ground or whose rays went under it are dropped (multipath ghosts, `below_ground_m`), then the points that other sweeps' rays saw through are removed as dynamic
(nuplan_occ.aggregation.dynamic). Objects: rigid categories accumulate over the whole scene, the others keep
their frame ids for a window around each frame. For carving, the background rays of each sweep that cross
the box of a rigid track of `through_categories` are kept in that box's frame (they show where the object
is not).

Inputs: `scene`, `background` (of the sweeps at `background_positions`), `aggregate_outliers`,
`registration`, `object_boxes`, `object_points` (of every loaded sweep), `observations` and
`observation_bits` (the lidar_rays stage's observation grids of the output frames, the dynamic test's
evidence from those sweeps; other evidence sweeps are cast here).
Outputs: `background_aggregate` (BackgroundAggregate, scene frame, m, its points in ascending scene x, so a
frame reads only the slice within its grid's reach), `objects` (track -> ObjectAggregate, box frame),
`object_through_rays` (rigid track of `through_categories` -> (starts (K, 3), ends (K, 3)), box frame, m),
`frame_movers` (output sweep position -> (n, 3) float32, scene frame: the sweep's own background points
where the aggregate removed points as dynamic), `aggregate_outliers_removed` (sweep position -> the
aggregate points of that sweep the outlier test removed; empty when the filter stage filtered the sweeps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.aggregation.aggregate import aggregate_background, aggregate_objects, without_outliers
from nuplan_occ.aggregation.carve import rays_through_boxes
from nuplan_occ.aggregation.dynamic import MOVER_CELL_M, movers_by_frame, seen_through
from nuplan_occ.aggregation.split import cleared_background
from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import BOX_CATEGORIES
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.points.below_ground import below_ground
from nuplan_occ.rays.observations import split_observation_bits
from nuplan_occ.rays.visibility import lidar_observation_bits
from nuplan_occ.sequences import MappedSequence


@dataclass(frozen=True)
class AggregateParams:
    voxel_downsample_m: float = param(0.05, "thin the background aggregate to one point per cube of this edge "
                                      "(0: keep all)", unit="m", low=0.0)
    crop_margin_m: float = param(5.0, "keep the background points within this margin of at least one output "
                                 "frame's grid (negative: keep all)", unit="m")
    rigid_categories: tuple[str, ...] = param(
        ("vehicle", "bicycle", "traffic_cone", "barrier", "czone_sign", "generic_object"),
        "categories aggregated over the whole scene; the others over a window of sweeps", choices=BOX_CATEGORIES)
    remove_dynamic: bool = param(True, "drop background points that other sweeps' rays saw through (movers)")
    dynamic_min_votes: int = param(2, "sweeps that must have seen through a point to remove it", low=1)
    dynamic_ground_clearance_m: float = param(0.3, "points this close above the local ground are never removed "
                                              "as dynamic", unit="m", low=0.0)
    dynamic_protect_dilation: int = param(1, "voxels around a sweep's returns in which that sweep does not vote",
                                          low=0)
    dynamic_occupied_ratio: float = param(0.5, "a point's votes must exceed this times the sweeps with a return "
                                          "in or next to its voxel", low=0.0)
    dynamic_sweep_stride: int = param(2, "every n-th loaded sweep's rays are dynamic evidence", low=1)
    dynamic_max_sweeps: int = param(50, "at most this many evidence sweeps, spread evenly over the scene (0: all)",
                                    low=0)
    object_clearance_m: float = param(0.2, "drop background points inside a corrected box grown by this, "
                                      "sideways and up (negative: keep them)", unit="m")
    ground_keep_m: float = param(0.03, "the grown box starts this high above the box's bottom (the ground around "
                                 "objects stays)", unit="m", low=0.0)
    max_range_m: float = param(75.0, "background points farther than this from their sweep's ego (x-y) are not "
                               "aggregated (0: no limit)", unit="m", low=0.0)
    below_ground_m: float = param(0.5, "background points lower than this under the cloud's ground (a low "
                                  "percentile per 1 m cell, lowest over 5 x 5 cells), or whose ray runs that "
                                  "low under a known ground on its way, are dropped: multipath ghosts (0: off)",
                                  unit="m", low=0.0)
    through_categories: tuple[str, ...] = param(("czone_sign",), "rigid categories whose tracks keep the background "
                                                "rays crossing their boxes, for carving", choices=BOX_CATEGORIES)


def run(inputs: dict, params: AggregateParams) -> dict:
    scene = inputs["scene"]
    ok = scene.ok_indices()
    with_background = inputs["background_positions"]
    poses = inputs["registration"].poses
    outputs = [i for i in ok if scene.sweeps[i].is_output]
    crop = None
    if params.crop_margin_m >= 0 and outputs:
        crop = (poses[outputs], DEFAULT_GRID.lower - params.crop_margin_m, DEFAULT_GRID.upper + params.crop_margin_m)

    def cleared(position: int) -> np.ndarray:  # when asked for: no second copy of every sweep's background
        return cleared_background(inputs["background"][position], inputs["object_boxes"][position],
                                  params.max_range_m, params.object_clearance_m, params.ground_keep_m)

    def observation_at(position: int) -> tuple[np.ndarray, np.ndarray]:  # the lidar_rays stage's, else cast here
        token, observations = scene.sweeps[position].token, inputs["observations"]
        if token in observations.tokens:
            return split_observation_bits(inputs["observation_bits"][observations.row(token)])
        return lidar_observation_bits(scene.sweeps[position].xyz, scene.sensor_origin_ego, DEFAULT_GRID)

    clouds = MappedSequence(with_background, cleared)
    background = aggregate_background(
        clouds,
        np.repeat(scene.sensor_origin_ego[None], len(with_background), axis=0),
        poses[with_background],
        T_global_from_scene=poses[ok[0]] if ok else None,
        voxel_downsample_m=params.voxel_downsample_m or None,
        crop=crop,
    )
    outliers_removed = {}
    if inputs["aggregate_outliers"] is not None:
        background, removed = without_outliers(background, inputs["aggregate_outliers"])
        outliers_removed = {position: int(n) for position, n in zip(with_background, removed)}
    if params.below_ground_m > 0:
        background = background.subset(~below_ground(background.points, params.below_ground_m,
                                                     origins=background.frame_origins[background.frame_ids]))
    frame_movers = {position: np.zeros((0, 3), np.float32) for position in outputs}
    if params.remove_dynamic and ok:
        used = scene.spread_positions(params.dynamic_sweep_stride, params.dynamic_max_sweeps)
        T_scene_from_ego = invert_transform(background.T_global_from_scene) @ poses[used]
        dynamic = seen_through(background.points, MappedSequence(used, observation_at), T_scene_from_ego,
                               min_votes=params.dynamic_min_votes,
                               ground_clearance_m=params.dynamic_ground_clearance_m,
                               protect_dilation=params.dynamic_protect_dilation,
                               occupied_ratio=params.dynamic_occupied_ratio)
        scene_from_global = invert_transform(background.T_global_from_scene)
        frame_movers = movers_by_frame(background.points, dynamic, ((p, cleared(p)) for p in outputs),
                                       {p: scene_from_global @ poses[p] for p in outputs},
                                       params.voxel_downsample_m or MOVER_CELL_M)
        background = background.subset(~dynamic)
    background = background.subset(np.argsort(background.points[:, 0], kind="stable"))
    objects = aggregate_objects([inputs["object_points"][i] for i in ok], [inputs["object_boxes"][i] for i in ok],
                                rigid_categories=params.rigid_categories)
    wanted = {track for track, aggregate in objects.items()
              if aggregate.rigid and aggregate.category in params.through_categories}
    object_through_rays = rays_through_boxes(MappedSequence(with_background, lambda i: inputs["background"][i]),
                                             [inputs["object_boxes"][i] for i in with_background],
                                             scene.sensor_origin_ego, wanted)
    return {"background_aggregate": background, "objects": objects, "object_through_rays": object_through_rays,
            "frame_movers": frame_movers, "aggregate_outliers_removed": outliers_removed}


STAGE = Stage("aggregate", inputs=("scene", "background", "background_positions", "aggregate_outliers", "registration",
                                   "object_boxes", "object_points", "observations", "observation_bits"),
              outputs=("background_aggregate", "objects", "object_through_rays", "frame_movers",
                       "aggregate_outliers_removed"),
              params_type=AggregateParams, run=run)
