"""Stage 5, aggregate (FBSA): the scene's background in one scene-local frame with the refined poses,
cropped to the output frames' grids plus a margin, with dynamic points removed by free-space evidence
(points that at least `dynamic_min_votes` sweeps' rays passed through, see nuplan_occ.aggregation.dynamic);
each track's points (from the track stage: taken inside its corrected boxes, in its corrected box
frame) accumulated (rigid classes over the whole scene, pedestrians over a short window around each frame). Per-point sensor origins are kept for normal orientation.
For space carving, the background rays of each frame that cross the box of a rigid track of `through_categories`
are kept in that box's frame (they show where the object is not).

The outlier test the filter stage left to the aggregate (`aggregate_outliers`, long scenes) runs on the
downsampled aggregate, before the dynamic test.

Inputs: `scene`, `background` (of the sweeps at `background_positions`), `aggregate_outliers`, `registration`, `object_boxes`,
`object_points` (of every loaded sweep), `observations` and `observation_bits` (the lidar_rays stage's
observation grids of the output frames, the dynamic test's evidence from those sweeps).
Outputs: `background_aggregate` (BackgroundAggregate, scene frame, its points in ascending scene x, so a
frame reads only the slice within its grid's reach), `objects` (track -> ObjectAggregate),
`object_through_rays` (rigid track of `through_categories` -> (starts (K, 3), ends (K, 3)), box frame, m), `frame_movers` (output
sweep position -> (n, 3) float32, scene frame: the sweep's own background points where the aggregate
removed points as dynamic), `aggregate_outliers_removed` (sweep position -> the aggregate points of that
sweep the outlier test removed; empty when the filter stage filtered the sweeps).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from nuplan_occ.aggregation.aggregate import BackgroundAggregate, aggregate_background, aggregate_objects, without_outliers
from nuplan_occ.aggregation.carve import segments_through_box
from nuplan_occ.aggregation.dynamic import seen_through
from nuplan_occ.aggregation.split import outside_boxes
from nuplan_occ.points.voxel_reduce import KeySet, voxel_keys
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.sequences import MappedSequence
from nuplan_occ.rays.visibility import lidar_observation_bits
from nuplan_occ.stages.visibility import RayObservations, split_observation_bits


@dataclass(frozen=True)
class AggregateParams:
    """voxel_downsample_m: thin the background aggregate to one point per cube of this edge (0 = keep all).
    crop_margin_m: keep only background points within this margin of the grid of at least one output frame
    (x, y, z box of DEFAULT_GRID in the frame's refined ego frame); negative = keep all. Points beyond every
    output grid only cost reconstruction time; the margin gives the solver context at the grid's edges.
    rigid_categories: classes aggregated over the whole scene; others use a window of frames.
    remove_dynamic: drop background points that other sweeps' rays saw through (moving objects outside their
    boxes, unboxed movers); dynamic_min_votes, dynamic_ground_clearance_m, dynamic_protect_dilation,
    dynamic_occupied_ratio: see nuplan_occ.aggregation.dynamic.seen_through (ratio 0.5 chosen by measurement on the
    bench: 0 removes more trail but also 1-3 % of static points on faces seen at grazing angles);
    dynamic_sweep_stride: use every n-th loaded sweep's rays as evidence (one ray traversal per used sweep);
    dynamic_max_sweeps: at most this many of them, spread evenly over the scene (`SceneData.spread_positions`;
    0 = all): a longer scene's points are seen by more sweeps than the vote needs (bench/report-scale.md notes).
    object_clearance_m: background points inside a corrected box grown by this much (sideways and up) are
    dropped (negative: keep them): an object's points that its logged box missed would otherwise become
    background, and a ghost trail where the object moves; ground_keep_m: the grown box starts this high
    above the box's bottom, so the ground around objects stays (0.03 m measured against 0.1 m on the bench:
    trail voxels 531 -> 484, nothing else changed).
    max_range_m: background points farther than this from their own sweep's ego (x-y distance, m) are not
    aggregated (0: no limit). Logs box agents only up to a range (the synthetic logs 80 m, nuPlan's annotation
    range is not documented), so beyond it moving vehicles have no box and their points would enter the
    background as a static ghost; the sweeps' rays cannot vote them out there either, as each sweep votes only
    inside its own grid. A point inside an output frame's grid is within 70.7 m of that frame's ego, so the
    scenery of every grid is still seen from the nearer sweeps (bench/report-scale.md notes: trails at 20 s).
    through_categories: rigid categories whose tracks get `object_through_rays`, the background rays that cross
    their boxes; the reconstruct stage carves these objects' solids with them too. Those rays start at the
    merged LiDAR frame's origin, the only sensor pose nuPlan stores, while the rig has five LiDARs mounted up
    to ~1 m away from it (synthetic rig: roof, A-pillars, front and back bumpers), so a ray that in truth
    passed over, beside or under an object (between its wheels) is redrawn through it; its error at the
    object is the origin's error scaled by the share of the ray still ahead of it, large for returns far
    beyond the object. The object's own rays end on its surface, where that error vanishes, so they keep
    carving. Measured on the 20 s scale bench (pooled IoU with / without them for every carved class):
    vehicle 0.642 / 0.655, barrier 0.614 / 0.676, generic object 0.710 / 0.805, czone sign 0.686 / 0.541.
    Czone signs keep them: their panel stands on thin legs, and only rays through the box show the empty
    space under the panel. Rays are gathered only for these categories (the other rigid tracks' were never
    used and took a tenth of the stage)."""

    voxel_downsample_m: float = 0.05
    crop_margin_m: float = 5.0
    rigid_categories: tuple[str, ...] = ("vehicle", "bicycle", "traffic_cone", "barrier", "czone_sign", "generic_object")
    remove_dynamic: bool = True
    dynamic_min_votes: int = 2
    dynamic_ground_clearance_m: float = 0.3
    dynamic_protect_dilation: int = 1
    dynamic_occupied_ratio: float = 0.5
    dynamic_sweep_stride: int = 2
    dynamic_max_sweeps: int = 50
    object_clearance_m: float = 0.2
    ground_keep_m: float = 0.03
    max_range_m: float = 75.0
    through_categories: tuple[str, ...] = ("czone_sign",)


MOVER_CELL_M = 0.05
"""Cell of the unboxed-mover lookup when the aggregate is not downsampled (m)."""


def movers_by_frame(background: BackgroundAggregate, dynamic: np.ndarray,
                    frame_clouds: Iterable[tuple[int, np.ndarray]], T_scene_from_ego: dict[int, np.ndarray],
                    voxel_m: float) -> dict[int, np.ndarray]:
    """Output sweep position -> (n, 3) float32 points, scene frame: the points of that sweep (frame_clouds:
    (position, points in its ego frame), placed by T_scene_from_ego) in a downsampling cell of voxel_m whose
    kept point was removed as dynamic: the sweep's unboxed movers, voxelized in that frame only
    (nuplan_occ.voxel.movers). The cell decides rather than the kept point itself, since a cell keeps the
    earliest frame's point and a mover covers cells it had crossed before. One sweep is moved into the
    scene frame at a time."""
    flagged = KeySet()
    flagged.new(voxel_keys(background.points[dynamic], voxel_m))
    movers = {}
    for position, cloud in frame_clouds:
        points = transform_points(T_scene_from_ego[position], cloud)
        movers[position] = points[flagged.holds(voxel_keys(points, voxel_m))].astype(np.float32)
    return movers


def rays_through_boxes(backgrounds: Sequence, boxes: Sequence, sensor_origin_ego: np.ndarray,
                       tracks: set[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Track -> (starts (K, 3), ends (K, 3)) in its box frame (m): the rays sensor_origin_ego -> return of every
    sweep's background (backgrounds[i] (N_i, 3), ego frame; read only for a sweep boxing one of them) that cross
    the track's box in that sweep (boxes[i], Boxes of the same sweep), for the tracks in `tracks`; a track boxed
    in some sweep gets an entry (maybe empty), the others none."""
    through: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for i, sweep_boxes in enumerate(boxes):
        listed = [k for k, track in enumerate(sweep_boxes.track_tokens) if track in tracks]
        if not listed:
            continue
        points = backgrounds[i]
        origins = np.broadcast_to(sensor_origin_ego, points.shape)
        for k in listed:
            through.setdefault(sweep_boxes.track_tokens[k], []).append(segments_through_box(
                origins, points, sweep_boxes.centers[k], float(sweep_boxes.yaws[k]), sweep_boxes.sizes[k]))
    return {track: (np.vstack([r[0] for r in rays]), np.vstack([r[1] for r in rays])) for track, rays in through.items()}


def cleared_background(background: Sequence, object_boxes: Sequence, position: int,
                       params: AggregateParams) -> np.ndarray:
    """The background (ego frame) of the sweep at `position` within max_range_m of its ego and without the
    points near its objects' corrected boxes (object_clearance_m < 0: as it is). Made when asked for, so that a scene never holds a second copy
    of every sweep's background (an output sweep is cleared twice: for the aggregate and for its movers; the
    compiled box test makes that cheaper than holding the copies)."""
    cloud = background[position]
    if params.max_range_m > 0:
        cloud = cloud[np.hypot(cloud[:, 0], cloud[:, 1]) <= params.max_range_m]
    if params.object_clearance_m < 0:
        return cloud
    return cloud[outside_boxes(cloud, object_boxes[position], params.object_clearance_m, params.ground_keep_m)]


def sweep_observation(scene, position: int, observations: RayObservations, observation_bits: Sequence
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The `lidar_observation_bits` of the sweep at `position`: the lidar_rays
    stage's when it is an output frame there, else cast from its returns."""
    token = scene.sweeps[position].token
    if token in observations.tokens:
        return split_observation_bits(observation_bits[observations.row(token)])
    return lidar_observation_bits(scene.sweeps[position].xyz, scene.sensor_origin_ego, DEFAULT_GRID)


def run(inputs: dict, params: AggregateParams) -> dict:
    scene = inputs["scene"]
    ok = scene.ok_indices()
    with_background = inputs["background_positions"]
    poses = inputs["registration"].poses
    outputs = [i for i in ok if scene.sweeps[i].is_output]
    crop = None
    if params.crop_margin_m >= 0 and outputs:
        crop = (poses[outputs], DEFAULT_GRID.lower - params.crop_margin_m, DEFAULT_GRID.upper + params.crop_margin_m)
    def cleared(position: int) -> np.ndarray:
        return cleared_background(inputs["background"], inputs["object_boxes"], position, params)

    def observation_at(position: int) -> np.ndarray:
        return sweep_observation(scene, position, inputs["observations"], inputs["observation_bits"])

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
        frame_movers = movers_by_frame(background, dynamic, ((p, cleared(p)) for p in outputs),
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
              params_type=AggregateParams,
              run=run,
              code=("nuplan_occ.aggregation.aggregate", "nuplan_occ.points.box_kernels", "nuplan_occ.points.outliers",
                    "nuplan_occ.points.knn", "nuplan_occ.aggregation.carve",
                    "nuplan_occ.aggregation.box_cull", "nuplan_occ.aggregation.dynamic", "nuplan_occ.aggregation.split",
                    "nuplan_occ.points.voxel_reduce",
                    "nuplan_occ.rays.visibility", "nuplan_occ.rays.traversal", "nuplan_occ.voxel.frame_lookup"),
              doc=__doc__ or "")
