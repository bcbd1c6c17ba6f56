"""Track refinement over one scene, in the sweeps' ego frames and the global frame: the stored boxes moved
into each sweep's ego frame with the refined poses, each box's points taken from its sweep, each track's
corrected boxes smoothed over time in the global frame, and small static objects' boxes moved onto their
points (box_snap). The per-track ICP itself is track_refine's.

`scene` is a nuplan_occ.pipeline.scene.SceneData; poses are the refined T_global_from_ego (F, 4, 4) of its
sweeps; boxes are nuplan_occ.io.types.Boxes; global poses of boxes are (x, y, z, yaw) in m and rad.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from nuplan_occ.geometry import invert_transform, transform_points, wrap_angle, yaw_matrix, yaw_of
from nuplan_occ.io.types import Boxes
from nuplan_occ.points.box_kernels import within_square
from nuplan_occ.tracks.box_snap import BoxSnapParams, snap_shift
from nuplan_occ.tracks.track_refine import TrackRefineParams, corrected_box, smooth_track_poses


def boxes_in_ego(scene, poses: np.ndarray, position: int) -> Boxes:
    """The sweep's stored boxes moved into its ego frame with the refined pose T_global_from_ego."""
    return scene.sweeps[position].boxes_global.transformed(invert_transform(poses[position]), "ego")


def robust_travel(xy: np.ndarray) -> float:
    """How far (m) a track's stored box centres (n, 2), in time order, travel: the largest distance between the
    medians of their first, middle and last thirds (per-box noise, which the largest single displacement
    would count, averages out)."""
    if len(xy) < 2:
        return 0.0
    thirds = [np.median(part, axis=0) for part in np.array_split(np.asarray(xy, np.float64), min(3, len(xy)))]
    return float(max(np.linalg.norm(a - b) for a in thirds for b in thirds))


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
    travel = robust_travel(stored[:, :2])
    static = float(np.median(speeds)) < params.static_speed_mps and travel < params.static_travel_m
    times = np.array([scene.sweeps[i].timestamp_us for i in positions], dtype=np.float64) / 1e6
    return smooth_track_poses(times, np.array(corrected), np.array(weights), static, params.smooth_window_s), static


def presmoothed_boxes(scene, poses: np.ndarray, initial: dict[int, Boxes], frames_of: dict[str, list[int]],
                      params: TrackRefineParams) -> dict[int, Boxes]:
    """`initial` (sweep position -> that sweep's boxes, ego frame) with every track's boxes smoothed over time in
    the global frame before any ICP (smoothed_global_poses with zero corrections): the starting boxes of the
    track ICP, whose model, built from the frames' points in these boxes, is then sharp where the stored boxes'
    independent per-frame errors would blur it."""
    smoothed = {track: smoothed_global_poses(scene, poses, initial, track, positions, np.zeros((len(positions), 4)),
                                             [0] * len(positions), params)[0]
                for track, positions in frames_of.items()}
    return {i: boxes_at_global_poses(boxes, invert_transform(poses[i]),
                                     [smoothed[track][frames_of[track].index(i)] for track in boxes.track_tokens])
            for i, boxes in initial.items()}


def snapped_static_poses(scene, poses: np.ndarray, static: dict[str, tuple[list[int], np.ndarray, np.ndarray]],
                         params: BoxSnapParams) -> dict[str, np.ndarray]:
    """track -> (4,) global pose (x, y, z, yaw) of each static track's box moved in x, y onto the points near
    it in its sweeps (nuplan_occ.tracks.box_snap; points taken to the global frame with the refined poses).
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


def boxes_at_global_poses(boxes: Boxes, T_ego_from_global: np.ndarray, global_poses: list[np.ndarray]) -> Boxes:
    """`boxes` (one sweep's, ego frame) with each box k moved to global_poses[k] ((4,) x, y, z, yaw in the
    global frame), expressed in that sweep's ego frame (T_ego_from_global); sizes and the rest unchanged."""
    centers, yaws = boxes.centers.copy(), boxes.yaws.copy()
    for k, pose in enumerate(global_poses):
        centers[k] = transform_points(T_ego_from_global, pose[None, :3])[0]
        yaws[k] = float(wrap_angle(pose[3] + yaw_of(T_ego_from_global[:3, :3])))
    return replace(boxes, centers=centers, yaws=yaws)
