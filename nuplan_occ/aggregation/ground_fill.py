"""Ground surface across the gaps between LiDAR rings, from the aggregated background (SCENE frame, metres;
z up, the scene frame being an upright ego pose).

Far from the sensor the rings of a sweep land metres apart on the ground, so a surface reconstruction
trimmed at a fraction of a metre from the points leaves the ground full of holes although rays observed
it. Here the ground is a height field: every xy cell whose lowest point lies within `above_low_m` of the
lowest point around it (`window_m`) gives a ground sample (see `ground_samples`), the samples are Delaunay-triangulated
in xy, and a triangle is kept when it is small (longest edge <= `max_edge_m`) and nearly flat (height
range <= `max_rise_m`), so gaps between rings are bridged but not walls, kerbs taller than the rise or
spans wider than the edge limit.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter
from scipy.spatial import Delaunay, QhullError

from nuplan_occ.points import PointInputError


def ground_samples(points: np.ndarray, cell_m: float, window_m: float, above_low_m: float,
                   band_m: float = 0.1) -> np.ndarray:
    """(G, 3) ground samples, one per xy cell of edge cell_m: the mean of the cell's points within band_m of
    its lowest point (less biased by range noise than the minimum), kept when that lowest point is within
    above_low_m of the lowest point of the cells within window_m / 2 around it."""
    keys = np.floor(points[:, :2] / cell_m).astype(np.int64)
    keys -= keys.min(axis=0)
    shape = tuple(keys.max(axis=0) + 1)
    lowest = np.full(shape, np.inf)
    np.minimum.at(lowest, (keys[:, 0], keys[:, 1]), points[:, 2])
    floor = minimum_filter(lowest, size=2 * int(np.ceil(window_m / 2 / cell_m)) + 1, mode="constant", cval=np.inf)
    low = lowest[keys[:, 0], keys[:, 1]]
    in_band = (points[:, 2] <= low + band_m) & (low <= floor[keys[:, 0], keys[:, 1]] + above_low_m)
    flat = keys[in_band, 0] * shape[1] + keys[in_band, 1]
    cells, inverse, count = np.unique(flat, return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=points[in_band, axis]) for axis in range(3)], axis=1)
    return sums / count[:, None]


def ground_fill_mesh(points_scene: np.ndarray, cell_m: float = 0.25, window_m: float = 2.0, above_low_m: float = 0.2,
                     max_edge_m: float = 3.0, max_rise_m: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) scene frame m, faces (F, 3) int64) of the ground height field of the background
    points `points_scene` (N, 3) (see the module doc); empty when there are fewer than 3 samples."""
    points = np.asarray(points_scene, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise PointInputError(f"ground_fill_mesh: points_scene must be finite (N, 3), got shape {points.shape}")
    if min(cell_m, window_m, max_edge_m) <= 0 or min(above_low_m, max_rise_m) < 0:
        raise PointInputError("ground_fill_mesh: cell_m, window_m, max_edge_m must be > 0, above_low_m, max_rise_m >= 0")
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    if len(points) < 3:
        return empty
    samples = ground_samples(points, cell_m, window_m, above_low_m)
    if len(samples) < 3:
        return empty
    try:
        faces = Delaunay(samples[:, :2]).simplices.astype(np.int64)
    except QhullError:
        return empty
    corners = samples[faces]
    edges = np.linalg.norm(corners[:, [1, 2, 0], :2] - corners[:, :, :2], axis=2).max(axis=1)
    rise = np.ptp(corners[:, :, 2], axis=1)
    faces = faces[(edges <= max_edge_m) & (rise <= max_rise_m)]
    if len(faces) == 0:
        return empty
    used, remapped = np.unique(faces, return_inverse=True)
    return samples[used], remapped.reshape(-1, 3)
