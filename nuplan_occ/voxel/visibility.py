"""Observed-voxel masks by exact ray traversal of the grid (LiDAR rays and camera rays).

Traversal: `nuplan_occ.voxel.traversal` (the voxels a segment passes through, exactly, ray by ray in
compiled kernels; slivers shorter than 1e-6 voxel may be skipped).

LiDAR (mask_lidar): the voxels strictly before the return point are observed free, the voxel holding
the return is observed occupied (occupied wins over another ray's free); the mask is free | occupied,
the rest unknown.

Camera (mask_camera): pinhole model with the calibration's K (lens distortion ignored: the frustum is
that of the undistorted image), OpenCV camera axes (x right, y down, z forward) for T_ego_from_camera.
Rays are cast through a sub-sampled pixel lattice whose angular step is `voxel_size / max_range_m`
(adjacent rays are at most one voxel apart at max range); along each ray the voxels up to and including
the first occupied one (and within max_range_m) are visible. Occupied voxels closer than `near_m` to the
camera (its own vehicle) do not occlude. Each ray is marched voxel by voxel and stops at its first
occupied voxel, so the voxels behind an obstacle are never visited.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import CameraCalibration
from nuplan_occ.voxel.traversal import grid_args, mark_traversed, mark_visible_to_first_hit

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
"""Values of `lidar_observation`."""


class VisibilityError(ValueError):
    """Malformed rays, points or camera calibration."""


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise VisibilityError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    return p


def lidar_observation(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """uint8 (X, Y, Z): UNKNOWN 0, FREE 1 (a ray passed through before its return), OCCUPIED 2 (holds a
    return; wins over free). points_ego (N, 3) returns, origins_ego (N, 3) or (3,) ray origins, metres
    in the ego frame."""
    points = _as_points(points_ego, "lidar_observation points_ego")
    origins = np.ascontiguousarray(np.broadcast_to(np.asarray(origins_ego, dtype=np.float64), points.shape))
    obs = np.zeros(int(np.prod(grid.shape)), dtype=np.uint8)
    mark_traversed(origins, np.ascontiguousarray(points), *grid_args(grid), obs, FREE)
    idx, inside = grid.point_to_index(points)
    idx = idx[inside]
    obs[(idx[:, 0] * grid.shape[1] + idx[:, 1]) * grid.shape[2] + idx[:, 2]] = OCCUPIED
    return obs.reshape(grid.shape)


def lidar_visibility(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z) mask_lidar: voxels observed (free or occupied) by the rays origin -> return point
    (points (N, 3), origins (N, 3) or (3,), metres in the ego frame)."""
    return lidar_observation(points_ego, origins_ego, grid) != UNKNOWN


def camera_rays(camera: CameraCalibration, angular_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (R, 3) in the ego frame of rays through a pixel lattice of the
    camera's image with about `angular_step_rad` between neighbours (pinhole, OpenCV axes)."""
    K = np.asarray(camera.K, dtype=np.float64)
    T = np.asarray(camera.T_ego_from_camera, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4) or K[0, 0] <= 0 or K[1, 1] <= 0 or camera.width <= 0 or camera.height <= 0:
        raise VisibilityError(f"camera {camera.channel}: invalid intrinsics/extrinsics/size")
    step_u = max(1.0, K[0, 0] * angular_step_rad)
    step_v = max(1.0, K[1, 1] * angular_step_rad)
    u = np.arange(step_u / 2.0, camera.width, step_u)
    v = np.arange(step_v / 2.0, camera.height, step_v)
    U, V = np.meshgrid(u, v, indexing="ij")
    x = (U.ravel() - K[0, 2] - K[0, 1] * (V.ravel() - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (V.ravel() - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=1)
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    return T[:3, 3].copy(), d_cam @ T[:3, :3].T


def camera_visibility(occupied: np.ndarray, cameras: list[CameraCalibration], grid: GridSpec = DEFAULT_GRID,
                      max_range_m: float = 60.0, angular_step_rad: float | None = None,
                      near_m: float = 0.5) -> np.ndarray:
    """bool (X, Y, Z) mask_camera: voxels some camera sees (see module doc). occupied: bool (X, Y, Z)
    occupancy in the ego frame; cameras: calibrations with T_ego_from_camera."""
    if tuple(occupied.shape) != tuple(grid.shape):
        raise VisibilityError(f"camera_visibility: occupied has shape {occupied.shape}, grid {grid.shape}")
    step = grid.voxel_size / max_range_m if angular_step_rad is None else angular_step_rad
    occ = np.asarray(occupied, dtype=bool).ravel()
    visible = np.zeros(occ.shape, dtype=bool)
    if not cameras:
        return visible.reshape(grid.shape)
    starts, ends = [], []
    for camera in cameras:
        origin, dirs = camera_rays(camera, step)
        starts.append(np.broadcast_to(origin, dirs.shape))
        ends.append(starts[-1] + dirs * max_range_m)
    mark_visible_to_first_hit(np.concatenate(starts), np.concatenate(ends), *grid_args(grid), occ, near_m / max_range_m,
                              visible)
    return visible.reshape(grid.shape)
