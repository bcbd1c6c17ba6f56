"""Unboxed movers of one frame: the frame's own LiDAR points that the aggregate removed as dynamic
(other sweeps' rays saw through where they are: a moving object the log has no box for, e.g. a missed
detection), turned into labeled voxels of that frame only, so such an object is occupied where it is now
and leaves no trail where it was.

A mover has no box, so its class is read from where it stands, its size and its motion, per cluster of its
voxels (voxels at most `gap_voxels` apart join one cluster, as parts of the object may have stayed in the
background). Moving things are vehicles, bicycles (nuPlan's class holds motorcycles too) and pedestrians;
the other box categories are static. A cluster is
- `other` when its lowest voxel is more than `ground_reach_m` above the ground of its column (road users
  stand on the ground; a flagged patch of canopy or facade does not);
- a vehicle when its footprint spans at least `vehicle_extent_m` along x or y (a car seen side-on, a truck
  or bus from any side: longer than any bicycle) and its top stands at most `vehicle_max_height_m` above its
  ground (no road vehicle is taller; a stretch of facade the dynamic test flagged can be);
- part of a vehicle when shorter but linked to a vehicle cluster by gaps of at most `fragment_reach_m`
  (through other clusters too: a vehicle's side seen in pieces, where parts stayed in the background);
- a bicycle from `bicycle_extent_m` (longer than a pedestrian) when it moved, its top stands at least
  `bicycle_min_height_m` above its ground (a rider) and it spans at most `bicycle_max_width_m` across its motion
  (a bicycle is narrow across the way it rides; the back of a car driving along the line of sight spans its
  whole width across it, and is lower). Its motion is read from the flagged points of the frames just before
  and after (`neighbours`): the shift of their mean within `motion_reach_m` of the cluster, over the points whose
  place holds flagged points in only one of the two; no such points in either, or a shift under a voxel, and
  the motion is unknown: not a bicycle. Moved: static structure the dynamic test flagged (through gaps, at
  grazing angles) is flagged in the same place in other frames too, while a cyclist has left its place within
  half a second. Clusters of which at least `static_fraction` of the points recur (`recurring`: their place
  holds flagged points in another frame) are `other`. The test does not serve vehicles: one moving along its
  length covers the cells it leaves;
- else `other` (a pedestrian, a car seen from behind, a fragment).
A class left out of `classes` is `other` too: the neutral label, for a class the rule does not give reliably
(a wrong class is worse than a generic one).
A bicycle stands on its wheels, whose lowest returns lie within the dynamic test's ground clearance and are
not flagged: in each column of a bicycle cluster whose lowest voxel is at most `bicycle_ground_fill_m` above
the column's ground voxel, the voxels from the ground voxel up to it are the bicycle's too (`over_ground`:
they replace the background there, as an object's voxel outranks the ground it stands on).
Clusters of fewer than `min_voxels` voxels are LiDAR noise and are not painted. Instance ids and flow stay
0 (unknown without a track).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.points.voxel_reduce import voxel_keys
from nuplan_occ.grid import DEFAULT_GRID, GridSpec, column_runs
from nuplan_occ.labels import BICYCLE, OTHER, VEHICLE
from nuplan_occ.voxel.compose import FrameGrids
from nuplan_occ.voxel.ground import ground_height_index
from nuplan_occ.voxel.voxel_clusters import chebyshev_clusters


@dataclass(frozen=True)
class MoverVoxels:
    """indices (K, 3) int64 voxels [x, y, z] of the grid; class_ids (K,) uint8 label id of each; over_ground
    (K,) bool: the voxel may replace background (a bicycle's wheel columns down to the ground), else it
    fills an empty voxel only."""

    indices: np.ndarray
    class_ids: np.ndarray
    over_ground: np.ndarray


def mover_voxels(points_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID, min_voxels: int = 2,
                 vehicle_extent_m: float = 2.5, gap_voxels: int = 1, bicycle_extent_m: float = 1.0,
                 recurring: np.ndarray | None = None, static_fraction: float = 0.2,
                 ground_height: np.ndarray | None = None, ground_reach_m: float = 0.75,
                 fragment_reach_m: float = 1.0, bicycle_ground_fill_m: float = 0.5,
                 classes: tuple[int, ...] = (VEHICLE, BICYCLE), bicycle_min_height_m: float = 0.0,
                 neighbours: tuple[np.ndarray, np.ndarray] | None = None, bicycle_max_width_m: float = np.inf,
                 motion_reach_m: float = 4.0, vehicle_max_height_m: float = np.inf) -> MoverVoxels:
    """The labeled voxels of a frame's unboxed-mover points (N, 3), ego frame, m (see module doc).
    classes: the class ids the rule may give (of VEHICLE, BICYCLE); a cluster it would give another is `other`.
    bicycle_min_height_m: a bicycle cluster's top must stand at least this high above its ground (its own height
    where the ground is unknown); vehicle_max_height_m: a vehicle cluster's top at most this high (m).
    neighbours: the flagged points (M, 3), ego frame of this frame, of an earlier and a later frame (None: the
    motion is not read and `bicycle_max_width_m` is not applied). bicycle_max_width_m: the widest a bicycle
    cluster spans across its motion, m. motion_reach_m: horizontal radius around a cluster's centre in which the
    neighbours' points tell its motion, m.
    recurring: (N,) bool, whether each point's place holds flagged points in the other frames too (None: no
    other frames to tell, so no cluster is known to have moved and none is a bicycle). ground_height: (X, Y)
    ground z per column, m, ego frame, NaN unknown (None, or unknown under a whole cluster: the cluster is
    taken as standing on it)."""
    idx, inside = grid.point_to_index(points_ego)
    recurring = np.ones(len(idx), dtype=bool) if recurring is None else np.asarray(recurring, dtype=bool)
    idx, point_voxel = np.unique(idx[inside], axis=0, return_inverse=True)
    if not len(idx):
        return MoverVoxels(np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros(0, bool))
    cluster_of, count = chebyshev_clusters(idx, 2 * gap_voxels + 1)
    sizes = np.bincount(cluster_of, minlength=count)
    span = (_cluster_max(idx[:, :2], cluster_of, count) + _cluster_max(-idx[:, :2], cluster_of, count) + 1
            ) * grid.voxel_size  # each cluster's x and y extent over its own voxels
    point_cluster = cluster_of[point_voxel.reshape(-1)]
    share = np.bincount(point_cluster, weights=recurring[inside], minlength=count) / np.maximum(
        np.bincount(point_cluster, minlength=count), 1)
    extent = span.max(axis=1)
    grounded = _standing(idx, cluster_of, count, grid, ground_height, ground_reach_m)
    height = _height(idx, cluster_of, count, grid, ground_height)
    vehicle = grounded & (extent >= vehicle_extent_m) & (height <= vehicle_max_height_m + 1e-9)
    fragment = np.zeros(count, dtype=bool)
    half_reach = int(round(fragment_reach_m / (2 * grid.voxel_size)))
    if half_reach and vehicle.any():  # clusters whose gaps are at most fragment_reach_m form one group
        groups, _ = chebyshev_clusters(idx, 2 * half_reach + 1)
        cluster_group = np.zeros(count, dtype=np.int64)
        cluster_group[cluster_of] = groups
        fragment = grounded & np.isin(cluster_group, cluster_group[vehicle])
    tall = height >= bicycle_min_height_m - 1e-9
    bicycle = grounded & ~(vehicle | fragment) & (extent >= bicycle_extent_m) & (share < static_fraction) & tall
    if neighbours is not None:
        centres = grid.index_to_center(idx)[:, :2]
        width = _width_across_motion(centres, cluster_of, count, bicycle, neighbours, motion_reach_m, grid.voxel_size)
        bicycle &= width <= bicycle_max_width_m + 1e-9  # NaN (motion unknown) is no bicycle
    cluster_class = np.select([~grounded, vehicle | fragment, bicycle],
                              [OTHER, VEHICLE, BICYCLE], OTHER).astype(np.uint8)
    cluster_class[~np.isin(cluster_class, classes)] = OTHER
    keep = sizes[cluster_of] >= min_voxels
    idx, class_ids = idx[keep], cluster_class[cluster_of[keep]]
    wheels = _down_to_ground(idx[class_ids == BICYCLE], grid, ground_height, bicycle_ground_fill_m)
    return MoverVoxels(np.vstack([idx, wheels]), np.r_[class_ids, np.full(len(wheels), BICYCLE, np.uint8)],
                       np.r_[np.zeros(len(idx), bool), np.ones(len(wheels), bool)])


def _cluster_max(values: np.ndarray, cluster_of: np.ndarray, count: int) -> np.ndarray:
    """(count, D) the largest of values (K, D) over each cluster's rows."""
    out = np.full((count, values.shape[1]), np.iinfo(np.int64).min, dtype=np.int64)
    np.maximum.at(out, cluster_of, values)
    return out


def _width_across_motion(centres: np.ndarray, cluster_of: np.ndarray, count: int, clusters: np.ndarray,
                         neighbours: tuple[np.ndarray, np.ndarray], reach_m: float, voxel_size: float) -> np.ndarray:
    """(count,) m: for each cluster flagged in clusters (count,) bool, the span of its voxel centres (K, 2), x-y
    m, across its motion plus one voxel; NaN for the others and where the motion is unknown (see module doc)."""
    width = np.full(count, np.nan)
    before, after = (np.asarray(n, dtype=np.float64).reshape(-1, 3) for n in neighbours)
    before, after = (before[~recurring_points(before, [after], voxel_size)],
                     after[~recurring_points(after, [before], voxel_size)])  # static places tell no motion
    for cluster in np.flatnonzero(clusters):
        own = centres[cluster_of == cluster]
        centre = own.mean(axis=0)
        near_before = before[np.hypot(*(before[:, :2] - centre).T) <= reach_m, :2]
        near_after = after[np.hypot(*(after[:, :2] - centre).T) <= reach_m, :2]
        if not len(near_before) or not len(near_after):
            continue
        motion = near_after.mean(axis=0) - near_before.mean(axis=0)
        length = float(np.hypot(*motion))
        if length < voxel_size:
            continue
        across = own @ (np.array([-motion[1], motion[0]]) / length)
        width[cluster] = float(np.ptp(across)) + voxel_size
    return width


def _down_to_ground(idx: np.ndarray, grid: GridSpec, ground_height: np.ndarray | None, reach_m: float) -> np.ndarray:
    """(K, 3) voxels from each column's ground voxel up to (not including) the lowest of the voxels idx
    (K0, 3) in that column, for the columns whose lowest voxel lies at most reach_m (whole voxels) above
    their known ground voxel."""
    if ground_height is None or not len(idx) or reach_m <= 0:
        return np.zeros((0, 3), np.int64)
    columns, column_of = np.unique(idx[:, :2], axis=0, return_inverse=True)
    lowest = np.full(len(columns), grid.shape[2], np.int64)
    np.minimum.at(lowest, column_of.reshape(-1), idx[:, 2])
    ground = ground_height_index(ground_height, grid)[columns[:, 0], columns[:, 1]]
    gap = lowest - ground
    reach = (ground >= 0) & (gap > 0) & (gap <= int(round(reach_m / grid.voxel_size)))
    columns, ground, gap = columns[reach], ground[reach], gap[reach]
    run, z = column_runs(ground, gap)
    return np.c_[columns[run], z].astype(np.int64)


def _height(idx: np.ndarray, cluster_of: np.ndarray, count: int, grid: GridSpec, ground_height: np.ndarray | None
            ) -> np.ndarray:
    """(count,) m per cluster: the top of its highest voxel above the lowest known ground of its columns, or above
    the bottom of its lowest voxel where none of its columns has a known ground."""
    top = np.full(count, -np.inf)
    np.maximum.at(top, cluster_of, grid.z_min + (idx[:, 2] + 1) * grid.voxel_size)
    base = np.full(count, np.inf)
    np.minimum.at(base, cluster_of, grid.z_min + idx[:, 2] * grid.voxel_size)
    if ground_height is not None:
        ground = ground_height[idx[:, 0], idx[:, 1]]
        known = np.isfinite(ground)
        floor = np.full(count, np.inf)
        np.minimum.at(floor, cluster_of[known], ground[known])
        base = np.where(np.isfinite(floor), floor, base)
    return top - base


def _standing(idx: np.ndarray, cluster_of: np.ndarray, count: int, grid: GridSpec, ground_height: np.ndarray | None,
              reach_m: float) -> np.ndarray:
    """(count,) bool per cluster: its lowest voxel centre (over the columns of known ground) lies at most reach_m
    above its column's ground; True where no column of the cluster has a known ground."""
    if ground_height is None:
        return np.ones(count, dtype=bool)
    above = grid.z_min + (idx[:, 2] + 0.5) * grid.voxel_size - ground_height[idx[:, 0], idx[:, 1]]
    lowest = np.full(count, np.inf)
    np.minimum.at(lowest, cluster_of[np.isfinite(above)], above[np.isfinite(above)])
    return (lowest <= reach_m + 1e-9) | np.isinf(lowest)


def recurring_points(points: np.ndarray, others: list[np.ndarray], cell_m: float) -> np.ndarray:
    """(N,) bool: whether each of the points (N, 3) shares its cell (edge cell_m, m; all points in one frame,
    e.g. the scene frame) with a point of any of the `others` ((M_k, 3) each)."""
    if not others:
        return np.zeros(len(points), dtype=bool)
    return np.isin(voxel_keys(points, cell_m), np.concatenate([voxel_keys(o, cell_m) for o in others]))


def neighbour_movers(frame_movers: dict[int, np.ndarray], position: int, frames: int) -> list[np.ndarray]:
    """The flagged points (scene frame) of the output frames `frames` before and after the one at `position`
    (frame_movers: output position -> (N, 3) scene-frame points): the `others` of `recurring_points`; []
    unless the scene has both."""
    positions = sorted(frame_movers)
    n = positions.index(position)
    if n - frames < 0 or n + frames >= len(positions):
        return []
    return [frame_movers[positions[n - frames]], frame_movers[positions[n + frames]]]


def movers_around(frame_movers: dict[int, np.ndarray], position: int, frames: int) -> dict[int, np.ndarray]:
    """Signed output frame step (-frames..frames, 0 left out) -> the flagged points (scene frame) of that output
    frame around the one at `position` (frame_movers: output position -> (N, 3) scene-frame points); steps past
    the scene's ends are left out."""
    positions = sorted(frame_movers)
    n = positions.index(position)
    return {step: frame_movers[positions[n + step]] for step in range(-frames, frames + 1)
            if step and 0 <= n + step < len(positions)}


def paint_empty(grids: FrameGrids, movers: MoverVoxels) -> int:
    """Give the empty voxels among `movers`, and their over_ground voxels that hold background, their class
    (instance and flow stay 0; a painted voxel is no longer background); returns how many were painted."""
    i, j, k = movers.indices.T
    paint = (grids.semantics[i, j, k] == 0) | (movers.over_ground & grids.occupied_background[i, j, k])
    i, j, k = i[paint], j[paint], k[paint]
    grids.semantics[i, j, k] = movers.class_ids[paint]
    grids.occupied_background[i, j, k] = False
    return int(paint.sum())
