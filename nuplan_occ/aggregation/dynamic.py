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

Frames: "scene" (the aggregate's frame, z up), "ego" per sweep. Units: metres. Deterministic; the points are
looked up in each sweep's grid by a compiled loop (nuplan_occ.voxel.frame_lookup's rigid move, no temporaries).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numba
import numpy as np

from nuplan_occ.points import PointInputError
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.points.voxel_reduce import KeySet, voxel_keys
from nuplan_occ.voxel.frame_lookup import moved_voxel
from nuplan_occ.rays.traversal import grid_args


@numba.njit(cache=True, inline="always")
def _cell(point, cell_m, first_x, first_y, columns):
    """Flat index of the xy cell holding point (3,): row (x index - first_x), column (y index - first_y)."""
    return (int(np.floor(point[0] / cell_m)) - first_x) * columns + int(np.floor(point[1] / cell_m)) - first_y


@numba.njit(cache=True)
def _height_above_lowest(points, cell_m, first_x, first_y, columns, lowest, out):
    """out[n] = z of points[n] minus the lowest z of its cell_m xy cell (`_cell`; flat `lowest` starts at inf)."""
    for n in range(points.shape[0]):
        cell = _cell(points[n], cell_m, first_x, first_y, columns)
        lowest[cell] = min(lowest[cell], points[n, 2])
    for n in range(points.shape[0]):
        out[n] = points[n, 2] - lowest[_cell(points[n], cell_m, first_x, first_y, columns)]


def height_above_ground(points_scene: np.ndarray, cell_m: float) -> np.ndarray:
    """(M,) height (m) of each point (M, 3) scene frame above the lowest point of its cell_m xy cell (cell
    (i, j) = [i, i + 1) x [j, j + 1) times cell_m; one dense row of cells per x index over the points' extent)."""
    points = np.ascontiguousarray(points_scene, dtype=np.float64)
    out = np.zeros(len(points))
    if not len(points):
        return out
    first = np.floor(points[:, :2].min(axis=0) / cell_m).astype(np.int64)
    count = np.floor(points[:, :2].max(axis=0) / cell_m).astype(np.int64) - first + 1
    lowest = np.full(int(count[0] * count[1]), np.inf)
    _height_above_lowest(points, float(cell_m), int(first[0]), int(first[1]), int(count[1]), lowest, out)
    return out


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


@numba.njit(cache=True)
def _count_votes(points, candidates, ys, first, last, ego_y, reach, T_ego_from_scene, lower, voxel_size, shape,
                 free_bits, blocked_bits, free, near_returns):
    """For the candidates[first:last] (indices into points (M, 3), scene frame) whose y (ys, m) is within reach
    of ego_y: the voxel of the sweep's grid holding the point (packed bits of the flat grids, np.packbits order)
    adds one to near_returns[n] when set in blocked_bits, else one to free[n] when set in free_bits."""
    for n in range(first, last):
        if abs(ys[n] - ego_y) > reach:
            continue
        v = moved_voxel(points, candidates[n], T_ego_from_scene, lower, voxel_size, shape)
        if v < 0:
            continue
        byte, bit = v >> 3, 7 - (v & 7)
        if (blocked_bits[byte] >> bit) & 1:
            near_returns[n] += 1
        elif (free_bits[byte] >> bit) & 1:
            free[n] += 1


def seen_through(
    points_scene: np.ndarray,
    observations: Sequence[tuple[np.ndarray, np.ndarray]],
    T_scene_from_ego: np.ndarray,
    grid: GridSpec = DEFAULT_GRID,
    min_votes: int = 2,
    ground_clearance_m: float = 0.3,
    ground_cell_m: float = 1.0,
    protect_dilation: int = 1,
    occupied_ratio: float = 0.5,
) -> np.ndarray:
    """bool (M,): the background points (M, 3), scene frame, to remove as dynamic (see module doc).

    observations: F pairs (observed bits, FREE bits) of sweep f's `lidar_observation` grid in its ego frame on
    `grid`, as `nuplan_occ.rays.visibility.lidar_observation_bits` gives them (any sequence, each read once; the
    returns' voxels are the observed ones that are not free); T_scene_from_ego (F, 4, 4) places sweep f in the
    scene frame. Only points inside a sweep's `grid` (its ego frame) can get its vote. protect_dilation:
    voxels (Chebyshev) around the sweep's occupied voxels in which it does not vote (0 = only the occupied
    voxels themselves); those sweeps count against removal, weighted by occupied_ratio (0 = not at all)."""
    points = np.asarray(points_scene, dtype=np.float64)
    T = np.asarray(T_scene_from_ego, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or T.shape != (len(observations), 4, 4):
        raise PointInputError(f"seen_through: need points (M, 3) and T_scene_from_ego ({len(observations)}, 4, 4), "
                             f"got {points.shape} and {T.shape}")
    if min_votes < 1:
        raise PointInputError(f"seen_through: min_votes must be >= 1, got {min_votes}")
    remove = np.zeros(len(points), dtype=bool)
    if not len(points):
        return remove
    candidates = np.flatnonzero(height_above_ground(points, ground_cell_m) > ground_clearance_m)
    candidates = candidates[np.argsort(points[candidates, 0], kind="stable")]  # by scene x: a sweep reads a slice
    xs, ys = points[candidates, 0], points[candidates, 1]
    reach = grid.reach
    voxels = int(np.prod(grid.shape))
    free = np.zeros(len(candidates), dtype=np.int32)
    near_returns = np.zeros(len(candidates), dtype=np.int32)
    for (observed_bits, free_bits), T_f in zip(observations, T):
        observed_bits, free_bits = np.asarray(observed_bits, np.uint8), np.asarray(free_bits, np.uint8)
        if observed_bits.shape != ((voxels + 7) // 8,) or free_bits.shape != observed_bits.shape:
            raise PointInputError(f"seen_through: observation bits of shapes {observed_bits.shape} / {free_bits.shape}, "
                                 f"expected ({(voxels + 7) // 8},) for a grid of {grid.shape}")
        blocked = np.unpackbits(observed_bits & ~free_bits, count=voxels).view(bool).reshape(grid.shape)
        if protect_dilation > 0:
            blocked = dilate(blocked, protect_dilation)
        ego_x = T_f[0, 3]  # only points within reach of the sweep's ego can be in its grid
        first, last = np.searchsorted(xs, ego_x - reach, "left"), np.searchsorted(xs, ego_x + reach, "right")
        _count_votes(points, candidates, ys, int(first), int(last), float(T_f[1, 3]), reach, invert_transform(T_f),
                     *grid_args(grid), free_bits, np.packbits(blocked.reshape(-1)), free, near_returns)
    remove[candidates[(free >= min_votes) & (free > occupied_ratio * near_returns)]] = True
    return remove


MOVER_CELL_M = 0.05
"""Cell of the unboxed-mover lookup (`movers_by_frame`) when the aggregate is not downsampled (m)."""


def movers_by_frame(points_scene: np.ndarray, dynamic: np.ndarray, frame_clouds: Iterable[tuple[int, np.ndarray]],
                    T_scene_from_ego: dict[int, np.ndarray], voxel_m: float) -> dict[int, np.ndarray]:
    """Output sweep position -> (n, 3) float32 points, scene frame: the points of that sweep (frame_clouds:
    (position, points in its ego frame), placed by T_scene_from_ego) in a downsampling cell of voxel_m (m)
    whose kept aggregate point (points_scene (M, 3), scene frame) was removed as dynamic (`dynamic` (M,) bool,
    `seen_through`): the sweep's unboxed movers, voxelized in that frame only (nuplan_occ.voxel.movers). The
    cell decides rather than the kept point itself, since a cell keeps the earliest frame's point and a mover
    covers cells it had crossed before. One sweep is moved into the scene frame at a time."""
    flagged = KeySet()
    flagged.new(voxel_keys(points_scene[dynamic], voxel_m))
    movers = {}
    for position, cloud in frame_clouds:
        points = transform_points(T_scene_from_ego[position], cloud)
        movers[position] = points[flagged.holds(voxel_keys(points, voxel_m))].astype(np.float32)
    return movers
