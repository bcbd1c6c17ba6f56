"""Free-space consistency of a frame's background with its own LiDAR rays.

The background surface of a frame comes from the whole scene's aggregate. Where the aggregate is sparse
(far rings, ground a mover hid most of the time) the reconstruction can stand where this frame's rays
show empty space: the ground surface bulging one voxel up along a mover's path, the height-field fill
bridging a road to a raised walkway across a gap. A background voxel is cleared (made empty) when

- rays passed through it (observed FREE: a ray crossed it before its return), this frame's or, as the
  background is static, another output frame's of the scene,
- no aggregated background point lies in it (nothing was ever measured there), and
- its centre lies more than `ground_margin_m` above the local ground height (the ground voxel itself is
  never cleared: rays graze it before they reach the ground further on).

Grids are indexed [x, y, z] in the EGO frame of the frame (see nuplan_occ.grid). Points are moved between
frames by `nuplan_occ.voxel.frame_lookup` (its arithmetic, not numpy's BLAS).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation

from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import DEFAULT_GRID, GridSpec, true_indices
from nuplan_occ.voxel.frame_lookup import any_bit_set, mark_points
from nuplan_occ.rays.traversal import grid_args


WINDOW_SLACK_M = 1e-6
"""Growth (m) of `grid_window`: covers the rounding of moving the grid's corners."""


def grid_window(T_points_from_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> tuple[np.ndarray, np.ndarray]:
    """(lower (3,), upper (3,)) m: the axis-aligned box, in the points' frame, holding the grid's box moved
    there by T_points_from_ego (4x4), grown by WINDOW_SLACK_M; no point outside it lies in the grid."""
    corners = np.array([[x, y, z] for x in (grid.x_min, grid.x_max) for y in (grid.y_min, grid.y_max)
                        for z in (grid.z_min, grid.z_max)], dtype=np.float64)
    moved = corners @ np.asarray(T_points_from_ego, dtype=np.float64)[:3, :3].T + T_points_from_ego[:3, 3]
    return moved.min(axis=0) - WINDOW_SLACK_M, moved.max(axis=0) + WINDOW_SLACK_M


def point_support(points: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                  T_ego_from_points: np.ndarray | None = None) -> np.ndarray:
    """bool (X, Y, Z): voxels holding at least one of points (N, 3, m), in the ego frame or moved into it by
    T_ego_from_points (4x4)."""
    T = np.eye(4) if T_ego_from_points is None else np.asarray(T_ego_from_points, dtype=np.float64)
    support = np.zeros(int(np.prod(grid.shape)) + 1, dtype=bool)  # + the spare element of `mark_points`
    mark_points(np.ascontiguousarray(points, dtype=np.float64), T, *grid_args(grid), support)
    return support[:-1].reshape(grid.shape)


def sorted_point_support(points_scene: np.ndarray, T_scene_from_ego: np.ndarray,
                         grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """`point_support` in the grid of the ego frame T_scene_from_ego (4x4) of points (M, 3), scene frame, m, in
    ascending scene x: only the slice within the x range of the grid's `grid_window` in the scene frame is
    looked at."""
    xs = points_scene[:, 0]
    window_lo, window_hi = grid_window(T_scene_from_ego, grid)
    near = slice(np.searchsorted(xs, window_lo[0]), np.searchsorted(xs, window_hi[0], "right"))
    return point_support(points_scene[near], grid, invert_transform(T_scene_from_ego))


def clearable_background(occupied_background: np.ndarray, support: np.ndarray, ground_height: np.ndarray | None,
                         grid: GridSpec = DEFAULT_GRID, ground_margin_m: float = 0.2) -> np.ndarray:
    """bool (X, Y, Z): background voxels that free-space evidence may clear: occupied, holding no aggregated
    point (support: bool (X, Y, Z) from `point_support`) and with the centre more than ground_margin_m above
    the local ground (ground_height (X, Y), metres in the ego frame; NaN columns and None are left alone)."""
    for name, array in (("occupied_background", occupied_background), ("support", support)):
        if tuple(array.shape) != tuple(grid.shape):
            raise ValueError(f"clearable_background: {name} has shape {array.shape}, expected {grid.shape}")
    if ground_height is None:
        return np.zeros(grid.shape, dtype=bool)
    z_centres = grid.z_min + (np.arange(grid.shape[2]) + 0.5) * grid.voxel_size
    with np.errstate(invalid="ignore"):
        above_ground = z_centres[None, None, :] > np.asarray(ground_height)[:, :, None] + ground_margin_m
    return occupied_background & ~support & above_ground


def crossed_objects(semantics: np.ndarray, classes: tuple[int, ...], object_points: np.ndarray, own_free_bits: np.ndarray,
                    grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z): voxels labeled one of `classes` (ids) that the frame's own rays crossed (set in its
    FREE bits own_free_bits, `lidar_observation_bits`) and that hold none of the objects' own points (object_points bool
    (X, Y, Z), `FrameGrids.object_points`). An object is where it is at this frame's time, so only this
    frame's rays speak about it; a voxel it only partly fills is crossed by rays that miss it, but usually
    also holds one of its points, which keeps it."""
    if tuple(semantics.shape) != tuple(grid.shape) or tuple(object_points.shape) != tuple(grid.shape):
        raise ValueError(f"crossed_objects: grids have shapes {semantics.shape} / {object_points.shape}, expected {grid.shape}")
    wanted = np.zeros(grid.shape, dtype=bool)
    for class_id in classes:  # one comparison per class: cheaper than a table lookup per voxel
        wanted |= semantics == class_id
    return free_voxels_in_frames(wanted & ~object_points, np.eye(4)[None],
                                 np.asarray(own_free_bits, dtype=np.uint8)[None], grid)


def crossed_far_from_points(candidates: np.ndarray, object_points: np.ndarray, own_free_bits: np.ndarray,
                            reach_m: float, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z): the candidate voxels (bool (X, Y, Z)) that the frame's own rays crossed (FREE bits
    own_free_bits) and whose column lies farther than reach_m (x-y, centre to centre) from every column holding
    an object's own point (object_points bool (X, Y, Z)). The end of a box from which no return came, at this
    frame or in the sweeps around it, while rays passed through it, is empty space the box covers; the voxels
    a surface partly fills lie near its returns and stay."""
    near = binary_dilation(object_points.any(axis=2), structure=grid.column_disc(reach_m))
    return free_voxels_in_frames(candidates & ~near[:, :, None], np.eye(4)[None],
                                 np.asarray(own_free_bits, dtype=np.uint8)[None], grid)


def free_in_other_frames(centres_ego: np.ndarray, T_other_from_ego: np.ndarray, free_bits: np.ndarray,
                         grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(N,) bool: voxel centres (N, 3, this frame's ego frame, m) that lie in a voxel another frame's rays
    crossed (set in that frame's FREE bits free_bits[f] (F, n_bytes) of `lidar_observation_bits`, its grid reached by
    T_other_from_ego[f] (F, 4, 4)). The background is static: space any frame saw through holds no
    background, whatever moved there at other times. A centre stops at the first frame that saw through it:
    the cost is (centres x frames) lookups at most."""
    n_bytes = (int(np.prod(grid.shape)) + 7) // 8
    bits = np.asarray(free_bits, dtype=np.uint8)
    transforms = np.asarray(T_other_from_ego, dtype=np.float64).reshape(-1, 4, 4)
    if bits.ndim != 2 or bits.shape[1] != n_bytes or len(bits) != len(transforms):
        raise ValueError(f"free_in_other_frames: packed bits have shape {bits.shape}, expected ({len(transforms)}, {n_bytes})")
    free = np.zeros(len(centres_ego), dtype=bool)
    any_bit_set(np.ascontiguousarray(centres_ego, dtype=np.float64), transforms, bits, *grid_args(grid), free)
    return free


def free_voxels_in_frames(candidates: np.ndarray, T_other_from_ego: np.ndarray, free_bits: np.ndarray,
                          grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z): the voxels of `candidates` (bool (X, Y, Z), this frame's grid) whose centre
    `free_in_other_frames` finds in some frame's crossed space (T_other_from_ego, free_bits as there)."""
    indices = true_indices(candidates)
    free = free_in_other_frames(grid.index_to_center(indices), T_other_from_ego, free_bits, grid)
    out = np.zeros(grid.shape, dtype=bool)
    out[tuple(indices[free].T)] = True
    return out
