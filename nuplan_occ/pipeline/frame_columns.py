"""Per-frame manifest columns computed from poses, boxes and the scene's map alignment: filter columns for the
spatial/temporal subsets and quality (QA) figures. numpy, and a numba kernel for the point coverage's
neighbourhood test."""

from __future__ import annotations

import numba
import numpy as np

from nuplan_occ.geometry import invert_transform, rotation_angle_deg
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import Boxes
from nuplan_occ.map_labels.map_align import MapAlignment
from nuplan_occ.voxel.frame_lookup import point_voxels

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


def frame_columns(scene, position: int, registration, speeds: np.ndarray, outliers: int, map_status: str,
                  alignment: MapAlignment | None) -> dict:
    """The columns of the frame at `position` of `scene` (SceneData) known before its grids: output_index (see
    `nuplan_occ.storage.clips`), filter columns (ego_speed from `speeds` (F,) m/s, `agent_speed_columns`) and
    QA figures: the refined pose's correction of the logged one (registration: the register stage's
    Registration), the sweep's stored points and those dropped on reading (non-finite, beyond a LiDAR's reach), `outliers` (points the outlier test removed), the map's status
    and the scene's map alignment (qa_map_*: NaN, or 0 points, without one)."""
    sweep = scene.sweeps[position]
    correction = invert_transform(sweep.logged_pose) @ registration.poses[position]  # in the logged ego frame
    return {
        "output_index": int(sweep.output_index),
        "ego_speed": float(speeds[position]),
        **agent_speed_columns(sweep.boxes_global),
        "qa_pose_correction_m": float(np.linalg.norm(correction[:3, 3])),
        "qa_pose_correction_deg": rotation_angle_deg(correction[:3, :3]),
        "qa_pose_accepted": bool(registration.accepted[position]),
        "qa_pose_fitness": float(registration.fitness[position]),
        "qa_points": len(sweep.stored_cloud) if sweep.has_cloud else 0,
        "qa_points_dropped": int(sweep.dropped_points),
        "qa_outliers_removed": int(outliers),
        "qa_map_status": map_status,
        "qa_map_aligned": bool(alignment is not None and alignment.applied),
        "qa_map_offset_m": float(np.hypot(alignment.dx, alignment.dy)) if alignment is not None else float("nan"),
        "qa_map_yaw_deg": float(np.degrees(alignment.dyaw)) if alignment is not None else float("nan"),
        "qa_map_paint_points": int(alignment.n_points) if alignment is not None else 0,
        "qa_map_paint_rms_m": float(alignment.rms_after) if alignment is not None else float("nan"),
    }


def point_coverage(points_ego: np.ndarray, occupied: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> float:
    """Fraction of a sweep's own returns inside the grid that fall in an occupied voxel or one of its
    26 neighbours (how well the grid explains the sweep); NaN with no returns inside the grid."""
    flat = point_voxels(points_ego, grid)
    flat = flat[flat >= 0]
    if len(flat) == 0:
        return float("nan")
    return _count_near_occupied(flat, np.ascontiguousarray(occupied, dtype=bool)) / len(flat)


@numba.njit(cache=True)
def _count_near_occupied(flat: np.ndarray, occupied: np.ndarray) -> int:
    """How many of the flat C-order voxel indices (N,), all inside `occupied` (X, Y, Z) bool, have an occupied
    voxel among themselves and their 26 neighbours."""
    count = 0
    _, columns, layers = occupied.shape
    for n in range(flat.shape[0]):
        column, k = divmod(flat[n], layers)
        i, j = divmod(column, columns)
        count += _occupied_around(occupied, i, j, k)
    return count


@numba.njit(cache=True)
def _occupied_around(occupied: np.ndarray, i: int, j: int, k: int) -> bool:
    """Whether voxel (i, j, k) or one of its 26 neighbours inside the grid is occupied (its own voxel first)."""
    if occupied[i, j, k]:
        return True
    shape = occupied.shape
    for a in range(max(i - 1, 0), min(i + 2, shape[0])):
        for b in range(max(j - 1, 0), min(j + 2, shape[1])):
            for c in range(max(k - 1, 0), min(k + 2, shape[2])):
                if occupied[a, b, c]:
                    return True
    return False
