"""Unboxed movers completed from the frames around them: each unboxed-mover cluster of a frame
(nuplan_occ.voxel.movers) of the given classes gathers the points of the frames around it
(nuplan_occ.voxel.mover_gathering); a vehicle's are filled as the solid they outline (`gathered_solids`), a
thin mover's are painted as they are (`gathered_traces`).

A vehicle is solid from the road up to its outline. In a grid of 0.25 m voxels its roof and its underside
occupy voxels that rays pass through without a return there (a ray grazing the roof, one passing under the
body), so its points alone leave those voxels out. The solid (`outline_solid`): every column of the ego
frame's grid whose centre lies inside the x-y convex hull of the gathered points, filled from the voxel above
the column's ground layer up to the voxel of its highest gathered point, or where it holds none, up to the
lowest of those tops among the columns within `reach_m` of it (centre to centre: a hole in a roof takes the
roof's height, a column beside the cabin the lower body's). A gathered point's own voxel outside the hull is
left: where the motion read is a little off, the points of other frames overhang the object's edge by part of
a voxel. Columns of unknown ground get none. The frame's own points keep the voxels they were painted
(nuplan_occ.voxel.movers).

Frames: ego frame of the frame painted, metres; voxels [x, y, z] of the grid.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.spatial import Delaunay, QhullError

from nuplan_occ.grid import DEFAULT_GRID, GridSpec, column_runs
from nuplan_occ.voxel.ground import ground_height_index
from nuplan_occ.voxel.mover_gathering import GatherSettings, gather_mover
from nuplan_occ.voxel.movers import MoverVoxels
from nuplan_occ.voxel.voxel_clusters import chebyshev_clusters

MIN_OWN_POINTS = 5
"""A cluster with fewer of the frame's own points is not gathered (too little to overlay)."""


def outline_solid(points: np.ndarray, ground_height: np.ndarray | None, reach_m: float,
                  grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(K, 3) int64 distinct voxels of the solid the points (N, 3) outline (module doc); ground_height (X, Y)
    m, NaN unknown (None: all unknown); none when the points span no x-y area."""
    idx, inside = grid.point_to_index(points)
    idx = idx[inside]
    if not len(idx):
        return np.zeros((0, 3), np.int64)
    disc = grid.column_disc(reach_m)
    radius = disc.shape[0] // 2
    lower = np.maximum(idx[:, :2].min(axis=0) - radius, 0)
    upper = np.minimum(idx[:, :2].max(axis=0) + radius, np.array(grid.shape[:2]) - 1)
    top = np.full(tuple(upper - lower + 1), -1, dtype=np.int64)
    np.maximum.at(top, tuple((idx[:, :2] - lower).T), idx[:, 2])
    unseen = grid.shape[2]  # above every layer: a column without points never sets the lowest top around it
    lowest_around = minimum_filter(np.where(top >= 0, top, unseen), footprint=disc, mode="constant", cval=unseen)
    reach_top = np.where(top >= 0, top, np.where(lowest_around < unseen, lowest_around, -1))
    ci, cj = np.nonzero(reach_top >= 0)
    try:
        centres = grid.index_to_center(np.c_[ci + lower[0], cj + lower[1], np.zeros(len(ci))])[:, :2]
        column = Delaunay(np.asarray(points, dtype=np.float64)[inside][:, :2]).find_simplex(centres) >= 0
    except QhullError:  # collinear or too few points: no hull, no solid
        return np.zeros((0, 3), np.int64)
    ci, cj = ci[column], cj[column]
    height = reach_top[ci, cj]
    ground = (np.full(len(ci), -1, np.int64) if ground_height is None
              else ground_height_index(ground_height, grid)[ci + lower[0], cj + lower[1]])
    keep = (ground >= 0) & (height > ground)
    ci, cj, ground, height = ci[keep] + lower[0], cj[keep] + lower[1], ground[keep], height[keep]
    run, z = column_runs(ground + 1, height - ground)
    return np.c_[ci[run], cj[run], z].astype(np.int64)


def _gathered_clusters(movers: MoverVoxels, own_points: np.ndarray, neighbours: dict[int, np.ndarray],
                       class_ids: tuple[int, ...], settings: GatherSettings, grid: GridSpec
                       ) -> list[tuple[int, np.ndarray]]:
    """(class id, gathered points (M, 3)) of each of the frame's mover clusters of class_ids holding at least
    MIN_OWN_POINTS of its own points (arguments as in `gathered_solids`)."""
    chosen = np.isin(movers.class_ids, np.asarray(class_ids, np.uint8))
    voxels, classes = movers.indices[chosen], movers.class_ids[chosen]
    if not len(voxels) or not len(own_points):
        return []
    cluster_of, count = chebyshev_clusters(voxels, 3)
    flat = np.ravel_multi_index(tuple(voxels.T), grid.shape)
    order = np.argsort(flat)
    idx, inside = grid.point_to_index(own_points)
    point_flat = np.ravel_multi_index(tuple(idx.T), grid.shape)
    slot = np.clip(np.searchsorted(flat[order], point_flat), 0, len(flat) - 1)
    hit = inside & (flat[order][slot] == point_flat)
    point_cluster = np.where(hit, cluster_of[order][slot], -1)
    out = []
    for cluster in range(count):
        own = own_points[point_cluster == cluster]
        if len(own) >= MIN_OWN_POINTS:
            out.append((int(classes[cluster_of == cluster][0]), gather_mover(own, neighbours, settings, grid.voxel_size)))
    return out


def _as_movers(parts: list[np.ndarray], labels: list[int]) -> MoverVoxels:
    """MoverVoxels of voxel arrays (K_i, 3) with one class each; they fill empty voxels only."""
    if not parts:
        return MoverVoxels(np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros(0, bool))
    indices = np.vstack(parts)
    classes = np.concatenate([np.full(len(part), label, np.uint8) for part, label in zip(parts, labels)])
    return MoverVoxels(indices, classes, np.zeros(len(indices), bool))


def gathered_solids(movers: MoverVoxels, own_points: np.ndarray, neighbours: dict[int, np.ndarray],
                    ground_height: np.ndarray | None, class_ids: tuple[int, ...], settings: GatherSettings,
                    reach_m: float, grid: GridSpec = DEFAULT_GRID) -> MoverVoxels:
    """The solids of the frame's mover clusters of class_ids (module doc). movers: the frame's mover voxels
    (`mover_voxels`); own_points (N, 3): the frame's flagged points; neighbours: signed output frame step ->
    that frame's flagged points (K, 3), all in this frame's ego frame (m). Each solid's voxels take its
    cluster's class and fill empty voxels only (over_ground False)."""
    gathered = _gathered_clusters(movers, own_points, neighbours, class_ids, settings, grid)
    return _as_movers([outline_solid(points, ground_height, reach_m, grid) for _, points in gathered],
                      [label for label, _ in gathered])


def gathered_traces(movers: MoverVoxels, own_points: np.ndarray, neighbours: dict[int, np.ndarray],
                    class_ids: tuple[int, ...], settings: GatherSettings, min_points: int,
                    grid: GridSpec = DEFAULT_GRID) -> MoverVoxels:
    """The voxels holding at least min_points of the points each of the frame's mover clusters of class_ids gathers
    from the neighbour frames (arguments as in `gathered_solids`), no solid: the sides of a thin mover (a cyclist)
    that this frame's rays missed and the frames just before or after saw. A voxel with fewer is left: a point or
    two of a frame overlaid a little off land beside the mover. They take the cluster's class and fill empty
    voxels only."""
    gathered = _gathered_clusters(movers, own_points, neighbours, class_ids, settings, grid)
    parts = []
    for _, points in gathered:
        idx, inside = grid.point_to_index(points)
        voxels, count = np.unique(idx[inside], axis=0, return_counts=True)
        parts.append(voxels[count >= min_points].astype(np.int64))
    return _as_movers(parts, [label for label, _ in gathered])
