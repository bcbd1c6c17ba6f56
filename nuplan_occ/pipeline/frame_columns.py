"""Per-frame manifest columns computed from poses and boxes: filter columns for the spatial/temporal
subsets and quality (QA) figures. Pure numpy."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import Boxes

MOVING_SPEED_MPS = 0.5
"""An agent whose box speed exceeds this counts as moving."""


def ego_speeds(poses: np.ndarray, timestamps_us: np.ndarray) -> np.ndarray:
    """(F,) ego speed in m/s from T_global_from_ego poses (F, 4, 4) by central differences in time."""
    positions = poses[:, :3, 3]
    if len(positions) < 2:
        return np.zeros(len(positions))
    seconds = np.asarray(timestamps_us, dtype=np.float64) * 1e-6
    velocity = np.gradient(positions, seconds, axis=0)
    return np.linalg.norm(velocity[:, :2], axis=1)


def agent_speed_columns(boxes: Boxes) -> dict[str, float | int]:
    """max_agent_speed (m/s, horizontal, 0 with no boxes) and n_moving_agents of one frame's boxes."""
    speeds = np.linalg.norm(boxes.velocities[:, :2], axis=1) if len(boxes) else np.zeros(0)
    return {
        "max_agent_speed": float(speeds.max()) if len(speeds) else 0.0,
        "n_moving_agents": int((speeds > MOVING_SPEED_MPS).sum()),
    }


def point_coverage(points_ego: np.ndarray, occupied: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> float:
    """Fraction of a sweep's own returns inside the grid that fall in an occupied voxel or one of its
    26 neighbours (how well the grid explains the sweep); NaN with no returns inside the grid."""
    index, inside = grid.point_to_index(points_ego)
    index = index[inside]
    if len(index) == 0:
        return float("nan")
    near = np.asarray(occupied, dtype=bool)
    for axis in range(3):  # the 3 x 3 x 3 neighbourhood is one step along each axis in turn
        grown = near.copy()
        lower, upper = [slice(None)] * 3, [slice(None)] * 3
        lower[axis], upper[axis] = slice(None, -1), slice(1, None)
        grown[tuple(lower)] |= near[tuple(upper)]
        grown[tuple(upper)] |= near[tuple(lower)]
        near = grown
    return float(near[index[:, 0], index[:, 1], index[:, 2]].mean())
