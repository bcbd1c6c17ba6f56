"""track: refine every track's box at every sweep against the track's own points.

The stored boxes, moved into each sweep's ego frame with the refined ego pose and smoothed over time in the
global frame (as below, before any ICP: the per-frame errors of auto-labelled boxes, averaged away, would
otherwise blur the model each frame is registered to), are the starting point; each track's points of each
sweep (those inside its box) are registered to the points of its other sweeps
(nuplan_occ.tracks.track_refine: 4-DoF point-to-plane ICP, the model rebuilt `rounds` times), which removes
the box noise and the ego-pose error from the boxes at once, since the points are exact in their sweep's ego
frame. The corrected boxes are then smoothed over time in the global frame (a static track gets one pose, a
moving one a local quadratic fit), which also places the boxes of sweeps with too few points for ICP. A small
static object's box is then moved onto its own points (nuplan_occ.tracks.box_snap): an offset shared by all its
sweeps (the ego-pose error) is invisible to the ICP. Each sweep's points are then taken again from the whole
sweep, inside the corrected boxes, so points a misplaced box had cut off come back. Before all this, a track
whose boxes hold no point above their floor is dropped (a box on nothing gets no voxels); at the end, the boxes
of `fit_categories` grow to hold their track's points (an undersized box keeps its whole object) and those of
`shrink_categories` shrink to them (an oversized box draws no empty volume; nuplan_occ.tracks.box_fit).

Inputs: `scene`, `registration`, `map_alignment` (the boxes are placed with the registered poses corrected by
it, `boxes_on_map`). Outputs: `object_boxes` (sweep position -> Boxes in that sweep's ego frame,
corrected), `object_points` (sweep position -> track -> (points (n, 3), sensor origins (n, 3)) in the track's
corrected box frame, m), `track_corrections` (track -> (F, 4) ICP corrections (dx, dy, dz m, dyaw rad) of its
sweeps' smoothed stored boxes, zeros where not estimated).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.labels import BOX_CATEGORIES
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.settings import settings_from
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.tracks.box_snap import BoxSnapParams
from nuplan_occ.aggregation.split import points_per_box
from nuplan_occ.tracks.scene_tracks import (boxes_at_global_poses, boxes_in_ego, presmoothed_boxes,
                                            smoothed_global_poses, snapped_static_poses)
from nuplan_occ.tracks.track_refine import TrackRefineParams, refine_track
from nuplan_occ.tracks.box_fit import BoxFitParams, fitted_boxes, fitted_extents
from nuplan_occ.tracks.track_repair import empty_tracks, track_heights, track_views, without_tracks

REFINE = TrackRefineParams  # the library's defaults
SNAP = BoxSnapParams
FIT = BoxFitParams


@dataclass(frozen=True)
class TrackParams:
    rounds: int = param(REFINE.rounds, "model rebuilds of a track's ICP", low=1)
    icp_iterations: int = param(REFINE.icp_iterations, "ICP iterations per sweep and round", low=1)
    min_points: int = param(REFINE.min_points, "a sweep with fewer of the track's points gets no correction", low=1)
    min_frames: int = param(REFINE.min_frames, "tracks seen in fewer sweeps are not refined", low=2)
    max_distance_m: float = param(REFINE.max_distance_m, "correspondences farther apart are ignored", unit="m",
                                  low=0.0, low_open=True)
    huber_m: float = param(REFINE.huber_m, "residual scale of the robust weights", unit="m", low=0.0, low_open=True)
    prior_translation_m: float = param(REFINE.prior_translation_m, "1-sigma box position error pulling the "
                                       "corrections toward 0", unit="m", low=0.0, low_open=True)
    prior_yaw_deg: float = param(REFINE.prior_yaw_deg, "1-sigma box heading error pulling the corrections toward 0",
                                 unit="deg", low=0.0, low_open=True)
    model_voxel_m: float = param(REFINE.model_voxel_m, "the track's model keeps one point per cube of this edge",
                                 unit="m", low=0.0, low_open=True)
    normal_neighbors: int = param(REFINE.normal_neighbors, "points per normal estimate of the model", low=3)
    exclude_neighbors: int = param(REFINE.exclude_neighbors, "model points searched per point (its own sweep's "
                                   "skipped; the target is the mean of the rest)", low=1)
    smooth_window_s: float = param(REFINE.smooth_window_s, "half window of the global-frame smoothing of a moving "
                                   "track's boxes", unit="s", low=0.0)
    static_speed_mps: float = param(REFINE.static_speed_mps, "a track is static (one pose) when its boxes' median "
                                    "speed is below this and they stay within static_travel_m", unit="m/s", low=0.0)
    static_travel_m: float = param(REFINE.static_travel_m, "largest travel of a static track's boxes (between the "
                                   "medians of their first, middle and last thirds)", unit="m",
                                   low=0.0)
    weight_per_point: float = param(REFINE.weight_per_point, "smoothing weight of a corrected box per point (at most "
                                    "400 points; an uncorrected box weighs 1)", low=0.0)
    snap_max_size_m: float = param(SNAP.max_size_m, "static boxes whose longer footprint side is at most this are "
                                   "moved onto their points", unit="m", low=0.0)
    snap_radius_m: float = param(SNAP.radius_m, "largest such shift (0: no snapping)", unit="m", low=0.0)
    snap_min_height_m: float = param(SNAP.min_height_m, "snapped-to points lie at least this far above the local "
                                     "ground", unit="m", low=0.0)
    empty_clearance_m: float = param(0.3, "a track's points count as its object's from this high above its boxes' "
                                     "bottom", unit="m", low=0.0)
    empty_min_points: int = param(1, "a track with fewer such points over all its sweeps is dropped: a box on "
                                  "nothing gets no voxels (0: keep every track)", low=0)
    empty_min_share: float = param(0.1, "... and so is a track whose such points are fewer than this share of all the "
                                   "points its boxes hold (a box on the road)", low=0.0, high=1.0)
    fit_margin_m: float = param(FIT.grow_margin_m, "boxes of fit_categories grow, about their centre and by at most "
                                "this per side, to hold their track's points (0: off)", unit="m", low=0.0)
    fit_categories: tuple[str, ...] = param(FIT.grow_categories, "categories whose corrected boxes are grown to their "
                                            "points", choices=BOX_CATEGORIES)
    shrink_categories: tuple[str, ...] = param(FIT.shrink_categories, "categories whose corrected boxes shrink to "
                                               "their track's points (an oversized box draws no empty volume)",
                                               choices=BOX_CATEGORIES)
    shrink_max: float = param(FIT.max_shrink, "largest share of a box's length, width or height a shrink removes "
                              "(0: off)", low=0.0, high=1.0)
    shrink_quantile: float = param(FIT.shrink_quantile, "a shrink keeps this share of the track's points' reach on "
                                   "each axis", low=0.0, high=1.0)
    shrink_pad_m: float = param(FIT.pad_m, "a shrunk box reaches this far beyond its points", unit="m", low=0.0)
    shrink_raise_m: float = param(FIT.raise_max_m, "the top of a box of shrink_categories rises by at most this to "
                                  "hold its track's points above it (a box too low for its object)", unit="m", low=0.0)
    boxes_on_map: bool = param(True, "place the log's boxes with the poses corrected against the map's paint (the "
                               "label_map stage; the written ego_to_global): a scene's offset or turn against the "
                               "global frame, which the map shows and the boxes share, moves no box off its points "
                               "(False, or no alignment: the registered poses)")
    snap_keep_ratio: float = param(SNAP.keep_ratio, "a box already holding this share of the best shift's points "
                                   "stays", low=0.0, high=1.0)


def run(inputs: dict, params: TrackParams) -> dict:
    scene = inputs["scene"]
    poses = inputs["registration"].poses
    if params.boxes_on_map and inputs["map_alignment"] is not None:
        poses = inputs["map_alignment"].correction @ poses
    refine = settings_from(TrackRefineParams, params)
    ok = scene.ok_indices()
    origin = np.asarray(scene.sensor_origin_ego, dtype=np.float64)
    initial = {i: boxes_in_ego(scene, poses, i) for i in ok}
    if params.empty_min_points > 0:
        held = {i: points_per_box(scene.sweeps[i].xyz, initial[i], origin) for i in ok}
        empty = empty_tracks(track_views(initial, held), track_heights(initial), params.empty_clearance_m,
                             params.empty_min_points, params.empty_min_share)
        initial = {i: without_tracks(boxes, empty) for i, boxes in initial.items()}
    frames_of: dict[str, list[int]] = {}
    for i in ok:
        for track in initial[i].track_tokens:
            frames_of.setdefault(track, []).append(i)
    initial = presmoothed_boxes(scene, poses, initial, frames_of, refine)
    first_points = {i: points_per_box(scene.sweeps[i].xyz, initial[i], origin) for i in ok}
    corrections = {}
    for track, positions in frames_of.items():
        views = [first_points[i].get(track, (np.zeros((0, 3)), None))[0] for i in positions]
        corrections[track] = refine_track(views, refine)
    snap = BoxSnapParams(max_size_m=params.snap_max_size_m, radius_m=params.snap_radius_m,
                         min_height_m=params.snap_min_height_m, keep_ratio=params.snap_keep_ratio)
    final, to_snap = {}, {}
    for track, positions in frames_of.items():
        final[track], static = smoothed_global_poses(scene, poses, initial, track, positions, corrections[track],
                                                     [len(first_points[i].get(track, ((),))[0]) for i in positions],
                                                     refine)
        first = initial[positions[0]]
        size = first.sizes[first.track_tokens.index(track)]
        if static and params.snap_radius_m > 0 and float(np.max(size[:2])) <= params.snap_max_size_m:
            to_snap[track] = (positions, final[track][0], size)
    for track, pose in snapped_static_poses(scene, poses, to_snap, snap).items():
        final[track][:] = pose
    object_boxes, object_points = {}, {}
    for i in ok:
        boxes = initial[i]
        object_boxes[i] = boxes_at_global_poses(boxes, invert_transform(poses[i]),
                                                [final[track][frames_of[track].index(i)] for track in boxes.track_tokens])
    fit = BoxFitParams(grow_margin_m=params.fit_margin_m, grow_categories=params.fit_categories,
                       shrink_categories=params.shrink_categories, max_shrink=params.shrink_max,
                       shrink_quantile=params.shrink_quantile, pad_m=params.shrink_pad_m,
                       floor_clearance_m=params.empty_clearance_m, raise_max_m=params.shrink_raise_m)
    object_boxes = fitted_boxes(object_boxes, fitted_extents(object_boxes, lambda i: scene.sweeps[i].xyz, origin, fit))
    for i in ok:
        object_points[i] = points_per_box(scene.sweeps[i].xyz, object_boxes[i], origin)
    track_corrections = {track: corrections[track] for track in frames_of}
    return {"object_boxes": object_boxes, "object_points": object_points, "track_corrections": track_corrections}


STAGE = Stage("track", inputs=("scene", "registration", "map_alignment"), outputs=("object_boxes", "object_points", "track_corrections"),
              params_type=TrackParams, run=run, kept=True)
