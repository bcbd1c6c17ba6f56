"""Observed-voxel masks by exact ray traversal of the grid (LiDAR rays and camera rays). Pure numpy.

Ray traversal (exact, vectorized, chunked): a segment from a to b (ego metres) is clipped to the grid
box; in voxel units the voxels it passes through are the voxel at its (clipped) start plus, for every
lattice plane it crosses, the voxel it enters there, found by evaluating the segment a hair (1e-6
voxel) after the crossing. All crossings of all rays of a chunk are generated at once (ragged arange),
so there is no per-step Python loop. Slivers shorter than 1e-6 voxel may be skipped.

LiDAR (mask_lidar): the voxels strictly before the return point are observed free, the voxel holding
the return is observed occupied; the mask is free | occupied, the rest unknown.

Camera (mask_camera): pinhole model with the calibration's K (lens distortion ignored: the frustum is
that of the undistorted image), OpenCV camera axes (x right, y down, z forward) for T_ego_from_camera.
Rays are cast through a sub-sampled pixel lattice whose angular step is `voxel_size / max_range_m`
(adjacent rays are at most one voxel apart at max range); along each ray the voxels up to and including
the first occupied one (and within max_range_m) are visible. Occupied voxels closer than `near_m` to the
camera (its own vehicle) do not occlude.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import CameraCalibration

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
"""Values of `lidar_observation`."""

ENTRY_CHUNK = 4_000_000
"""Ray/voxel entries generated at once (bounds temporary memory)."""

_NUDGE = 1e-6


class VisibilityError(ValueError):
    """Malformed rays, points or camera calibration."""


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise VisibilityError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    return p


def _clip_to_box(o: np.ndarray, d: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter range [t0, t1] within [0, 1] of segments o + t d (voxel units) inside [0, shape]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (0.0 - o) / d
        tb = (shape - o) / d
    t_lo = np.where(d == 0, np.where((o >= 0) & (o < shape), -np.inf, np.inf), np.minimum(ta, tb))
    t_hi = np.where(d == 0, np.where((o >= 0) & (o < shape), np.inf, -np.inf), np.maximum(ta, tb))
    return np.maximum(t_lo.max(axis=1), 0.0), np.minimum(t_hi.min(axis=1), 1.0)


def _plane_ranges(o: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First plane index (N, 3) and number of planes (N, 3) crossed per axis between t0 and t1."""
    a, b = o + t0[:, None] * d, o + t1[:, None] * d
    first = np.floor(np.minimum(a, b)).astype(np.int64) + 1
    count = np.floor(np.maximum(a, b)).astype(np.int64) - first + 1
    return first, np.where(d == 0, 0, np.maximum(count, 0))


def _segment_entries(o: np.ndarray, d: np.ndarray, t0: np.ndarray, t1: np.ndarray, first: np.ndarray,
                     count: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxels entered by segments (one chunk): (ray index, flat voxel index, entry t), inside the grid.

    The start voxel is entered at t0; a voxel entered by crossing a plane at t >= t1 is not listed."""
    inv_len = _NUDGE / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    ray_ids, ts = [np.arange(len(o))], [t0]
    for axis in range(3):
        n = count[:, axis]
        ids = np.repeat(np.arange(len(o)), n)
        offset = np.arange(len(ids)) - np.repeat(np.cumsum(n) - n, n)
        k = first[ids, axis] + offset
        ray_ids.append(ids)
        ts.append((k - o[ids, axis]) / d[ids, axis])
    ids, t = np.concatenate(ray_ids), np.concatenate(ts)
    keep = t < t1[ids]
    keep[: len(o)] = True
    ids, t = ids[keep], t[keep]
    vox = np.floor(o[ids] + (t + inv_len[ids])[:, None] * d[ids]).astype(np.int64)
    inside = np.all((vox >= 0) & (vox < shape), axis=1)
    ids, t, vox = ids[inside], t[inside], vox[inside]
    flat = (vox[:, 0] * shape[1] + vox[:, 1]) * shape[2] + vox[:, 2]
    return ids, flat, t


def traverse(starts_ego: np.ndarray, ends_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID):
    """Yield, chunk by chunk, the voxels segments pass through: (ray index (global), flat voxel index in
    the grid (C order), entry parameter t in [0, 1)). starts/ends (N, 3) metres in the ego frame."""
    shape = np.asarray(grid.shape)
    o_all = (starts_ego - grid.lower) / grid.voxel_size
    d_all = (ends_ego - grid.lower) / grid.voxel_size - o_all
    t0, t1 = _clip_to_box(o_all, d_all, shape.astype(np.float64))
    rays = np.flatnonzero(t0 < t1)
    first, count = _plane_ranges(o_all[rays], d_all[rays], t0[rays], t1[rays])
    if len(rays) == 0:
        return
    cum = np.cumsum(count.sum(axis=1) + 1)
    cuts = np.searchsorted(cum, np.arange(ENTRY_CHUNK, cum[-1], ENTRY_CHUNK), side="right")
    edges = np.unique(np.concatenate([[0], cuts, [len(rays)]]))
    for start, stop in zip(edges[:-1], edges[1:]):
        r = rays[start:stop]
        ids, flat, t = _segment_entries(o_all[r], d_all[r], t0[r], t1[r], first[start:stop], count[start:stop], shape)
        yield r[ids], flat, t


def lidar_observation(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """uint8 (X, Y, Z): UNKNOWN 0, FREE 1 (a ray passed through before its return), OCCUPIED 2 (holds a
    return; wins over free). points_ego (N, 3) returns, origins_ego (N, 3) or (3,) ray origins, metres
    in the ego frame."""
    points = _as_points(points_ego, "lidar_observation points_ego")
    origins = np.broadcast_to(np.asarray(origins_ego, dtype=np.float64), points.shape)
    obs = np.zeros(int(np.prod(grid.shape)), dtype=np.uint8)
    for _, flat, _ in traverse(origins, points, grid):
        obs[flat] = FREE
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
    for camera in cameras:
        origin, dirs = camera_rays(camera, step)
        starts = np.broadcast_to(origin, dirs.shape)
        near_t = near_m / max_range_m
        for ids, flat, t in traverse(starts, starts + dirs * max_range_m, grid):
            blocking = occ[flat] & (t >= near_t)
            t_hit = np.full(int(ids.max()) + 1 if len(ids) else 0, np.inf)
            np.minimum.at(t_hit, ids[blocking], t[blocking])
            visible[flat[t <= t_hit[ids]]] = True
    return visible.reshape(grid.shape)
