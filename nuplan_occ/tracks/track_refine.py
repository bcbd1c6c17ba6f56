"""Per-frame refinement of a track's boxes against the track's own aggregated points.

Logged boxes are noisy (auto-labels: centre, heading and height jitter from frame to frame) and, moved
into a frame's ego frame, also carry that frame's ego-pose error. The points, however, are exact in the
ego frame of their sweep. So each frame's points of a track, taken into the box frame by that frame's
box, are registered to the track's model (its points of all other frames) with a 4-DoF point-to-plane
ICP (x, y, z, yaw about the box's z axis; boxes stay upright), and the correction found is the error of
that frame's box. The model is rebuilt from the corrected frames and the registration repeated.

Frames: "box" = the frame's (logged) box frame (origin at the box centre, x along the heading, z up);
"model" = the track's corrected box frame, shared by all frames. A correction c = (dx, dy, dz, dyaw)
maps box-frame points of its frame into the model frame: p_model = Rz(dyaw) p_box + (dx, dy, dz).
The corrections' gauge (the model frame itself) is fixed by giving them zero weighted mean, so the model
sits where the boxes put it on average (box noise is unbiased; its mean is the best anchor there is).
Units: metres, radians. numpy, and compiled kernels for the ICP (`track_icp`); deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.aggregate import voxel_first_indices
from nuplan_occ.points.knn import KdTree
from nuplan_occ.points.plane_normals import pca_normals
from nuplan_occ.tracks.track_icp import icp_4dof
from nuplan_occ.geometry import wrap_angle, yaw_matrix


@dataclass(frozen=True)
class TrackRefineParams:
    """Settings of a track's refinement (the track stage declares each one's meaning, unit and range).

    rounds: model rebuilds; icp_iterations: per frame and round; min_points: a frame with fewer points gets no
    correction (zero); min_frames: tracks seen in fewer frames are left alone; max_distance_m: correspondences
    farther apart are ignored (m); huber_m: residual scale of the robust weights (m); prior_translation_m /
    prior_yaw_deg: 1-sigma size of a box error, pulling the corrections toward 0 (directions the points do not
    constrain stay at 0); model_voxel_m: the model keeps one point per cube of this edge (m);
    normal_neighbors: points per normal estimate; exclude_neighbors: model points searched per point (those of
    its own frame skipped, the target is the mean of the rest). Smoothing in the global frame
    (`smooth_track_poses`): smooth_window_s half window (s); a track whose boxes' median speed is below
    static_speed_mps (m/s) and whose boxes stay within static_travel_m (m) is static (one pose);
    weight_per_point: a corrected frame weighs 1 + this * its points (at most 400), an uncorrected one 1."""

    rounds: int = 3
    icp_iterations: int = 8
    min_points: int = 30
    min_frames: int = 3
    max_distance_m: float = 0.4
    huber_m: float = 0.1
    prior_translation_m: float = 0.3
    prior_yaw_deg: float = 3.0
    model_voxel_m: float = 0.05
    normal_neighbors: int = 10
    exclude_neighbors: int = 8
    smooth_window_s: float = 1.0
    static_speed_mps: float = 0.3
    static_travel_m: float = 0.5
    weight_per_point: float = 0.04


def apply_correction(points_box: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """(n, 3) points moved from their frame's box frame into the model frame by correction (4,)."""
    c = np.asarray(correction, dtype=np.float64)
    return np.asarray(points_box, dtype=np.float64) @ yaw_matrix(c[3]).T + c[:3]


def corrected_box(center: np.ndarray, yaw: float, correction: np.ndarray) -> tuple[np.ndarray, float]:
    """The model frame's pose (centre (3,), yaw) in the frame the box (center, yaw) is given in (e.g. ego):
    T_frame_from_model = T_frame_from_box @ inverse(correction)."""
    c = np.asarray(correction, dtype=np.float64)
    offset = -(yaw_matrix(-c[3]) @ c[:3])  # origin of the model frame, in box coordinates
    new_center = np.asarray(center, dtype=np.float64) + yaw_matrix(yaw) @ offset
    return new_center, float(wrap_angle(yaw - c[3]))


def estimate_normals(points: np.ndarray, tree: KdTree, neighbors: int) -> np.ndarray:
    """(n, 3) unit normals (smallest principal axis of each point's `neighbors` nearest points; the sign is
    arbitrary, which point-to-plane ICP does not see)."""
    k = min(neighbors, len(points))
    _, idx = tree.query(points, k=k)
    return pca_normals(tree.data, idx.reshape(len(points), k).astype(np.int64))


@dataclass
class TrackModel:
    """A track's points in the model frame with their normals and source frame ids, and a k-d tree."""

    points: np.ndarray
    normals: np.ndarray
    frame_ids: np.ndarray
    tree: KdTree


def build_model(frames: list[np.ndarray], corrections: np.ndarray, params: TrackRefineParams) -> TrackModel:
    """The model of a track from its per-frame box-frame points (list of (n_i, 3)) and corrections (F, 4)."""
    pts = [apply_correction(p, c) for p, c in zip(frames, corrections)]
    ids = [np.full(len(p), i, dtype=np.int64) for i, p in enumerate(frames)]
    all_points = np.vstack(pts)
    keep = voxel_first_indices(all_points, params.model_voxel_m)
    points, frame_ids = all_points[keep], np.concatenate(ids)[keep]
    tree = KdTree(points)
    return TrackModel(points, estimate_normals(points, tree, params.normal_neighbors), frame_ids, tree)


def register_frame(points_box: np.ndarray, frame_id: int, model: TrackModel, start: np.ndarray,
                   params: TrackRefineParams) -> np.ndarray:
    """Correction (4,) of one frame: 4-DoF point-to-plane ICP of its box-frame points to the model's points
    of OTHER frames, Huber-weighted, with a Gaussian prior pulling the correction toward zero."""
    prior = np.array([1.0 / params.prior_translation_m ** 2] * 3 + [1.0 / np.radians(params.prior_yaw_deg) ** 2])
    return icp_4dof(np.ascontiguousarray(points_box, dtype=np.float64), int(frame_id), model.points, model.normals,
                    model.frame_ids, model.tree.kernel_arrays, np.asarray(start, dtype=np.float64),
                    prior, min(params.exclude_neighbors, len(model.points)), params.icp_iterations,
                    params.max_distance_m, params.huber_m, params.min_points)


def fix_gauge(corrections: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Corrections (F, 4) composed with the inverse of their weighted mean so that they average to zero."""
    if weights.sum() <= 0:
        return corrections
    mean = (corrections * weights[:, None]).sum(axis=0) / weights.sum()
    out = corrections.copy()
    out[:, 3] -= mean[3]
    out[:, :3] = (corrections[:, :3] - mean[:3]) @ yaw_matrix(-mean[3]).T
    return out


def refine_track(frames: list[np.ndarray], params: TrackRefineParams = TrackRefineParams()) -> np.ndarray:
    """(F, 4) corrections (dx, dy, dz, dyaw) of a track's F frames, given each frame's points in its own box
    frame (list of (n_i, 3) arrays, m). Frames with fewer than min_points points, and every frame of a track
    seen in fewer than min_frames frames, get zeros."""
    for i, p in enumerate(frames):
        if np.asarray(p).ndim != 2 or np.asarray(p).shape[1] != 3:
            raise PointInputError(f"refine_track: frame {i} points must be (n, 3), got {np.asarray(p).shape}")
    F = len(frames)
    frames = [np.asarray(p, dtype=np.float64) for p in frames]
    corrections = np.zeros((F, 4))
    usable = np.array([len(p) >= params.min_points for p in frames], dtype=bool)
    if usable.sum() < params.min_frames:
        return corrections
    weights = np.array([len(p) for p in frames], dtype=np.float64) * usable
    for _ in range(params.rounds):
        model = build_model(frames, corrections, params)
        for i in np.flatnonzero(usable):
            corrections[i] = register_frame(frames[i], int(i), model, corrections[i], params)
        corrections = fix_gauge(corrections, weights)
    corrections[~usable] = 0.0
    return corrections



def smooth_track_poses(times_s: np.ndarray, poses: np.ndarray, weights: np.ndarray, static: bool,
                       window_s: float) -> np.ndarray:
    """(F, 4) smoothed box poses (x, y, z m, yaw rad) of one track in a fixed (global) frame.

    Box errors are independent from frame to frame while objects move smoothly, so: a static track gets
    one pose for all frames (weighted mean; circular mean of yaw); a moving one, at each frame, the value
    of a weighted quadratic in time fitted to the frames within +-window_s (lower degree with fewer
    frames). times_s (F,) s; poses (F, 4); weights (F,) > 0, e.g. larger for frames corrected by ICP.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    t = np.asarray(times_s, dtype=np.float64).reshape(-1)
    if len(poses) < 2:
        return poses.copy()
    values = np.column_stack([poses[:, :3], np.unwrap(poses[:, 3])])
    if static:
        mean = (values * w[:, None]).sum(axis=0) / w.sum()
        mean[3] = np.arctan2((w * np.sin(poses[:, 3])).sum(), (w * np.cos(poses[:, 3])).sum())
        return np.repeat(mean[None], len(poses), axis=0)
    out = np.empty_like(values)
    for f in range(len(t)):
        near = np.abs(t - t[f]) <= window_s
        degree = int(min(2, near.sum() - 1))
        dt = t[near] - t[f]
        A = np.vander(dt, degree + 1, increasing=True) * np.sqrt(w[near])[:, None]
        coef, *_ = np.linalg.lstsq(A, values[near] * np.sqrt(w[near])[:, None], rcond=None)
        out[f] = coef[0]
    out[:, 3] = wrap_angle(out[:, 3])
    return out
