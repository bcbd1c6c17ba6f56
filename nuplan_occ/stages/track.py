"""Stage 4, track (FBSA): refine every track's box at every frame against the track's own points.

The stored boxes, moved into each sweep's ego frame with the refined ego pose, are the starting point;
each track's points of each frame (those inside its box) are registered to the points of its other
frames (nuplan_occ.tracks.track_refine: 4-DoF point-to-plane ICP, model rebuilt `rounds` times), which
removes the box noise and the ego-pose error from the boxes at once, since the points are exact in their
sweep's ego frame. The corrected boxes are then smoothed over time in the global frame (a static
track gets one pose, a moving one a local quadratic fit), which also places the boxes of frames with
too few points for ICP (cones, pedestrians) better than one noisy box can. A small static object's box
is then moved onto its own points (fbsa.box_snap): an offset shared by all its frames (the ego-pose
error) is invisible to the ICP, and would leave a cone's box empty. Then each frame's points are taken
again from the whole sweep, inside the corrected box, so points a misplaced box had cut off come back.

Inputs: `scene`, `registration`. Outputs: `object_boxes` (sweep position -> Boxes in that sweep's ego
frame, corrected where the track had enough points there), `object_points` (sweep position -> track ->
(points (n, 3), sensor origins (n, 3)) in the track's corrected box frame, m), `track_corrections`
(track -> (F, 4) corrections (dx, dy, dz m, dyaw rad) of its frames, zeros where not estimated).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from nuplan_occ.points.box_kernels import within_square
from nuplan_occ.tracks.box_snap import BoxSnapParams, snap_shift
from nuplan_occ.aggregation.split import foreground_by_track, points_in_boxes
from nuplan_occ.tracks.track_refine import TrackRefineParams, corrected_box, refine_track, smooth_track_poses
from nuplan_occ.geometry import invert_transform, transform_points, wrap_angle, yaw_matrix, yaw_of
from nuplan_occ.io.types import Boxes
from nuplan_occ.pipeline.stage import Stage


def boxes_in_ego(scene, poses: np.ndarray, position: int) -> Boxes:
    """The sweep's stored boxes moved into its ego frame with the refined pose T_global_from_ego."""
    return scene.sweeps[position].boxes_global.transformed(invert_transform(poses[position]), "ego")


def points_per_box(cloud_ego: np.ndarray, boxes: Boxes, origin_ego: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """track -> (points, sensor origins) in that box's frame, for the points (ego frame) inside each box."""
    points, origins = foreground_by_track(cloud_ego, points_in_boxes(cloud_ego, boxes), boxes, origin_ego)
    return {track: (points[track], origins[track]) for track in points}


def smoothed_global_poses(scene, poses: np.ndarray, initial: dict[int, Boxes], track: str, positions: list[int],
                          corrections: np.ndarray, n_points: list[int], params: TrackRefineParams
                          ) -> tuple[np.ndarray, bool]:
    """((F, 4) global poses (x, y, z, yaw), static) of one track's boxes at its sweeps `positions`: each
    box corrected by its ICP correction, moved to the global frame with the refined pose, then smoothed
    (static tracks: one pose; see track_refine.smooth_track_poses)."""
    corrected, stored, speeds, weights = [], [], [], []
    for i, c, n in zip(positions, corrections, n_points):
        boxes = initial[i]
        k = boxes.track_tokens.index(track)
        center, yaw = corrected_box(boxes.centers[k], float(boxes.yaws[k]), c)
        to_global = poses[i]
        corrected.append([*transform_points(to_global, center[None])[0], yaw + yaw_of(to_global[:3, :3])])
        stored.append(transform_points(to_global, boxes.centers[k][None])[0])
        speeds.append(float(np.linalg.norm(boxes.velocities[k][:2])))
        weights.append(1.0 + params.weight_per_point * min(n, 400) if np.any(c != 0) else 1.0)
    stored = np.array(stored)
    travel = float(np.max(np.linalg.norm(stored[:, :2] - stored[:1, :2], axis=1))) if len(stored) else 0.0
    static = float(np.median(speeds)) < params.static_speed_mps and travel < params.static_travel_m
    times = np.array([scene.sweeps[i].timestamp_us for i in positions], dtype=np.float64) / 1e6
    return smooth_track_poses(times, np.array(corrected), np.array(weights), static, params.smooth_window_s), static


def snapped_static_poses(scene, poses: np.ndarray, static: dict[str, tuple[list[int], np.ndarray, np.ndarray]],
                         params: BoxSnapParams) -> dict[str, np.ndarray]:
    """track -> (4,) global pose (x, y, z, yaw) of each static track's box moved in x, y onto the points near
    it in its sweeps (fbsa.box_snap; points taken to the global frame with the refined poses).
    static: track -> (its sweep positions, its (4,) global pose, its box size (3,)). One pass over the
    sweeps, each read once; only the points within the snap's height band (BoxSnapParams.z_band_m) are kept."""
    gathered: dict[str, list[np.ndarray]] = {track: [] for track in static}
    R = {track: yaw_matrix(float(pose[3])) for track, (_, pose, _) in static.items()}  # box from global axes
    tracks_at: dict[int, list[str]] = {}
    for track, (positions, _, _) in static.items():
        for i in positions:
            tracks_at.setdefault(i, []).append(track)
    for i in sorted(tracks_at):
        xyz = scene.sweeps[i].xyz
        T_ego_from_global = invert_transform(poses[i])
        for track in tracks_at[i]:
            _, pose, size = static[track]
            reach = params.radius_m + float(np.max(size[:2]))  # a square around the box, wider than needed
            center_ego = transform_points(T_ego_from_global, pose[None, :3])[0]
            near = within_square(xyz, float(center_ego[0]), float(center_ego[1]), reach)
            local = (transform_points(poses[i], xyz[near]) - pose[:3]) @ R[track]
            gathered[track].append(local[np.abs(local[:, 2]) <= float(size[2]) / 2.0 + params.z_band_m])
    snapped = {}
    for track, (_, pose, size) in static.items():
        shift = snap_shift(np.vstack(gathered[track]), size, params)
        snapped[track] = np.array(pose, dtype=np.float64)
        snapped[track][:2] += R[track][:2, :2] @ shift
    return snapped


def run(inputs: dict, params: TrackRefineParams) -> dict:
    scene = inputs["scene"]
    poses = inputs["registration"].poses
    ok = scene.ok_indices()
    origin = np.asarray(scene.sensor_origin_ego, dtype=np.float64)
    initial = {i: boxes_in_ego(scene, poses, i) for i in ok}
    first_points = {i: points_per_box(scene.sweeps[i].xyz, initial[i], origin) for i in ok}
    frames_of: dict[str, list[int]] = {}
    for i in ok:
        for track in initial[i].track_tokens:
            frames_of.setdefault(track, []).append(i)
    corrections = {}
    for track, positions in frames_of.items():
        views = [first_points[i].get(track, (np.zeros((0, 3)), None))[0] for i in positions]
        corrections[track] = refine_track(views, params)
    snap = BoxSnapParams(max_size_m=params.snap_max_size_m, radius_m=params.snap_radius_m,
                         min_height_m=params.snap_min_height_m, keep_ratio=params.snap_keep_ratio)
    final, to_snap = {}, {}
    for track, positions in frames_of.items():
        final[track], static = smoothed_global_poses(scene, poses, initial, track, positions, corrections[track],
                                                     [len(first_points[i].get(track, ((),))[0]) for i in positions],
                                                     params)
        first = initial[positions[0]]
        size = first.sizes[first.track_tokens.index(track)]
        if static and params.snap_radius_m > 0 and float(np.max(size[:2])) <= params.snap_max_size_m:
            to_snap[track] = (positions, final[track][0], size)
    for track, pose in snapped_static_poses(scene, poses, to_snap, snap).items():
        final[track][:] = pose
    object_boxes, object_points = {}, {}
    for i in ok:
        boxes = initial[i]
        centers, yaws = boxes.centers.copy(), boxes.yaws.copy()
        T_ego_from_global = invert_transform(poses[i])
        for k, track in enumerate(boxes.track_tokens):
            g = final[track][frames_of[track].index(i)]
            centers[k] = transform_points(T_ego_from_global, g[None, :3])[0]
            yaws[k] = float(wrap_angle(g[3] + yaw_of(T_ego_from_global[:3, :3])))
        object_boxes[i] = replace(boxes, centers=centers, yaws=yaws)
        object_points[i] = points_per_box(scene.sweeps[i].xyz, object_boxes[i], origin)
    track_corrections = {track: corrections[track] for track in frames_of}
    return {"object_boxes": object_boxes, "object_points": object_points, "track_corrections": track_corrections}


STAGE = Stage("track", inputs=("scene", "registration"), outputs=("object_boxes", "object_points", "track_corrections"),
              params_type=TrackRefineParams, run=run,
              code=("nuplan_occ.tracks.track_refine", "nuplan_occ.aggregation.split", "nuplan_occ.points.box_kernels",
                    "nuplan_occ.tracks.box_snap", "nuplan_occ.aggregation.aggregate", "nuplan_occ.points.voxel_reduce"),
              doc=__doc__ or "")
