"""Unboxed movers of one frame: the frame's own LiDAR points that the aggregate removed as dynamic
(other sweeps' rays saw through where they are: a moving object the log has no box for, e.g. a missed
detection), turned into labeled voxels of that frame only, so such an object is occupied where it is now
and leaves no trail where it was.

A mover has no box, so its class is read from its size: each cluster of its voxels (voxels at most
`gap_voxels` apart join one cluster, as parts of the object may have stayed in the background) is a
vehicle when its footprint spans at least `vehicle_extent_m` along x or y (a car seen side-on, a truck
or bus from any side: longer than any bicycle), else `other` (unclassified: a small flagged cluster may
be a cyclist, a pedestrian, a car seen from behind or static structure seen at a grazing angle);
clusters of fewer than `min_voxels` voxels are LiDAR noise and are not painted. Instance ids and flow
stay 0 (unknown without a track).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import OTHER, VEHICLE


@dataclass(frozen=True)
class MoverVoxels:
    """indices (K, 3) int64 voxels [x, y, z] of the grid; class_ids (K,) uint8 label id of each."""

    indices: np.ndarray
    class_ids: np.ndarray


def mover_voxels(points_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID, min_voxels: int = 2,
                 vehicle_extent_m: float = 2.5, gap_voxels: int = 1) -> MoverVoxels:
    """The labeled voxels of a frame's unboxed-mover points (N, 3), ego frame, m (see module doc)."""
    idx, inside = grid.point_to_index(points_ego)
    idx = np.unique(idx[inside], axis=0)
    if not len(idx):
        return MoverVoxels(np.zeros((0, 3), np.int64), np.zeros(0, np.uint8))
    low = idx.min(axis=0) - gap_voxels
    occupied = np.zeros(tuple(idx.max(axis=0) + gap_voxels - low + 1), dtype=bool)
    local = idx - low
    occupied[tuple(local.T)] = True
    neighbourhood = np.ones((3, 3, 3), dtype=bool)
    if gap_voxels:
        occupied = ndimage.binary_dilation(occupied, neighbourhood, iterations=gap_voxels)
    clusters, count = ndimage.label(occupied, structure=neighbourhood)
    cluster_of = clusters[tuple(local.T)] - 1
    sizes = np.bincount(cluster_of, minlength=count)
    own = np.zeros_like(clusters)
    own[tuple(local.T)] = cluster_of + 1  # each cluster's extent over its own voxels, not the dilation
    span = np.array([[(box[axis].stop - box[axis].start) * grid.voxel_size for axis in (0, 1)]
                     for box in ndimage.find_objects(own, max_label=count)])
    cluster_class = np.where(span.max(axis=1) >= vehicle_extent_m, VEHICLE, OTHER).astype(np.uint8)
    keep = sizes[cluster_of] >= min_voxels
    return MoverVoxels(idx[keep], cluster_class[cluster_of[keep]])
