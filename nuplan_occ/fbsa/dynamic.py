"""Dynamic points in the background aggregate, found by free-space evidence ("seen through").

A background point left by a moving object (outside its box, or an object without a box) sits in space
that other sweeps looked through: their rays passed its voxel and returned farther away. Each sweep's own
rays give an observation grid in its ego frame (`lidar_observation`: unknown / free / occupied); a point
gets one vote from every sweep that observed its voxel FREE and saw no return in that voxel or, with
`protect_dilation`, in the voxels around it (mixed returns at the edges of walls and poles make static
points look free to grazing rays). A point is dynamic when it has at least `min_votes` votes and more
than `occupied_ratio` times as many votes as sweeps with a return in or next to its voxel (a static
surface has returns there in most sweeps; a mover only while it passed), except near the ground: grazing
rays traverse the road's voxels, so points within `ground_clearance_m` of the local ground
(the lowest aggregated point of their `ground_cell_m` xy cell, scene frame) are never removed.

Frames: "scene" (the aggregate's frame, z up), "ego" per sweep. Units: metres. Pure numpy, deterministic.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.fbsa import FbsaInputError
from nuplan_occ.fbsa.voxel_reduce import voxel_keys
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.voxel.visibility import FREE, OCCUPIED, lidar_observation


def height_above_ground(points_scene: np.ndarray, cell_m: float) -> np.ndarray:
    """(M,) height (m) of each point (M, 3) scene frame above the lowest point of its cell_m xy cell."""
    columns = np.c_[points_scene[:, :2], np.zeros(len(points_scene))]  # z = 0: one packed key per xy cell
    _, cell = np.unique(voxel_keys(columns, cell_m), return_inverse=True)
    cell = cell.reshape(-1)
    lowest = np.full(int(cell.max()) + 1 if len(cell) else 0, np.inf)
    np.minimum.at(lowest, cell, points_scene[:, 2])
    return points_scene[:, 2] - lowest[cell]


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """bool grid dilated by a (2 radius + 1)^3 cube (separable shifts; nothing wraps around the edges)."""
    out = mask.copy()
    for axis in range(out.ndim):
        src = out.copy()
        n = out.shape[axis]
        for r in range(1, min(radius, n - 1) + 1):
            lo = [slice(None)] * out.ndim
            hi = [slice(None)] * out.ndim
            lo[axis], hi[axis] = slice(0, n - r), slice(r, n)
            out[tuple(lo)] |= src[tuple(hi)]
            out[tuple(hi)] |= src[tuple(lo)]
    return out


def seen_through(
    points_scene: np.ndarray,
    sweeps_ego: list[np.ndarray],
    T_scene_from_ego: np.ndarray,
    origin_ego: np.ndarray,
    grid: GridSpec = DEFAULT_GRID,
    min_votes: int = 2,
    ground_clearance_m: float = 0.3,
    ground_cell_m: float = 1.0,
    protect_dilation: int = 1,
    occupied_ratio: float = 0.5,
) -> np.ndarray:
    """bool (M,): the background points (M, 3), scene frame, to remove as dynamic (see module doc).

    sweeps_ego: F arrays (n_f, 3), every return of sweep f in its ego frame (the rays origin_ego -> return,
    origin_ego (3,) ego frame); T_scene_from_ego (F, 4, 4) places sweep f in the scene frame. Only points
    inside a sweep's `grid` (its ego frame) can get its vote. protect_dilation: voxels (Chebyshev) around the
    sweep's occupied voxels in which it does not vote (0 = only the occupied voxels themselves); those sweeps
count against removal, weighted by occupied_ratio (0 = not at all)."""
    points = np.asarray(points_scene, dtype=np.float64)
    T = np.asarray(T_scene_from_ego, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or T.shape != (len(sweeps_ego), 4, 4):
        raise FbsaInputError(f"seen_through: need points (M, 3) and T_scene_from_ego ({len(sweeps_ego)}, 4, 4), "
                             f"got {points.shape} and {T.shape}")
    if min_votes < 1:
        raise FbsaInputError(f"seen_through: min_votes must be >= 1, got {min_votes}")
    remove = np.zeros(len(points), dtype=bool)
    if not len(points):
        return remove
    candidates = np.flatnonzero(height_above_ground(points, ground_cell_m) > ground_clearance_m)
    candidates = candidates[np.argsort(points[candidates, 0], kind="stable")]  # by scene x: a sweep reads a slice
    xs, ys = points[candidates, 0], points[candidates, 1]
    reach = float(np.linalg.norm(np.maximum(np.abs(grid.lower), np.abs(grid.upper))))  # grid corner from the ego
    free = np.zeros(len(candidates), dtype=np.int32)
    near_returns = np.zeros(len(candidates), dtype=np.int32)
    shape = np.array(grid.shape)
    for cloud, T_f in zip(sweeps_ego, T):
        obs = lidar_observation(cloud, origin_ego, grid)
        blocked = dilate(obs == OCCUPIED, protect_dilation) if protect_dilation > 0 else obs == OCCUPIED
        ego_x, ego_y = T_f[0, 3], T_f[1, 3]  # only points within reach of the sweep's ego can be in its grid
        first, last = np.searchsorted(xs, ego_x - reach, "left"), np.searchsorted(xs, ego_x + reach, "right")
        around = first + np.flatnonzero(np.abs(ys[first:last] - ego_y) <= reach)
        idx, inside = grid.point_to_index(transform_points(invert_transform(T_f), points[candidates[around]]))
        flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
        near = inside & blocked.ravel()[flat]
        near_returns[around] += near
        free[around] += inside & (obs.ravel()[flat] == FREE) & ~near
    remove[candidates[(free >= min_votes) & (free > occupied_ratio * near_returns)]] = True
    return remove
