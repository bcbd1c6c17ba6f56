"""Free-space consistency of a frame's background with its own LiDAR rays. Pure numpy.

The background surface of a frame comes from the whole scene's aggregate. Where the aggregate is sparse
(far rings, ground a mover hid most of the time) the reconstruction can stand where this frame's rays
show empty space: the ground surface bulging one voxel up along a mover's path, the height-field fill
bridging a road to a raised walkway across a gap. A background voxel is cleared (made empty) when

- this frame's rays passed through it (observed FREE: a ray crossed it before its return),
- no aggregated background point lies in it (nothing was ever measured there), and
- its centre lies more than `ground_margin_m` above the local ground height (the ground voxel itself is
  never cleared: rays graze it before they reach the ground further on).

Grids are indexed [x, y, z] in the EGO frame of the frame (see nuplan_occ.grid).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.voxel.visibility import FREE


def point_support(points_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z): voxels holding at least one of points_ego (N, 3, ego frame, m)."""
    idx, inside = grid.point_to_index(points_ego)
    support = np.zeros(grid.shape, dtype=bool)
    support[tuple(idx[inside].T)] = True
    return support


def unsupported_free_voxels(occupied_background: np.ndarray, observation: np.ndarray, support: np.ndarray,
                            ground_height: np.ndarray | None, grid: GridSpec = DEFAULT_GRID,
                            ground_margin_m: float = 0.2) -> np.ndarray:
    """bool (X, Y, Z): background voxels to clear (see the module doc).

    occupied_background: bool (X, Y, Z); observation: uint8 (X, Y, Z) from `lidar_observation`;
    support: bool (X, Y, Z) from `point_support`; ground_height: (X, Y) metres in the ego frame, NaN where
    unknown (such columns are left alone); None leaves everything."""
    for name, array in (("occupied_background", occupied_background), ("observation", observation),
                        ("support", support)):
        if tuple(array.shape) != tuple(grid.shape):
            raise ValueError(f"unsupported_free_voxels: {name} has shape {array.shape}, expected {grid.shape}")
    if ground_height is None:
        return np.zeros(grid.shape, dtype=bool)
    z_centres = grid.z_min + (np.arange(grid.shape[2]) + 0.5) * grid.voxel_size
    with np.errstate(invalid="ignore"):
        above_ground = z_centres[None, None, :] > np.asarray(ground_height)[:, :, None] + ground_margin_m
    return occupied_background & (observation == FREE) & ~support & above_ground
