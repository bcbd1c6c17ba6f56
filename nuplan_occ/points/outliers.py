"""Statistical outlier filters for LiDAR points.

Every function takes points (N, 3) in metres in any one frame and returns a bool keep mask (N,).
Methods:
- "global": the paper's rule ||p - mu|| < k_sigma * sigma, mu the centroid and sigma the RMS distance to it.
- "knn": Open3D `remove_statistical_outlier(nb_neighbors, std_ratio)`: keep p iff 0 < d(p) < mean(d) +
  std_ratio * std(d), d(p) the mean distance to its nb_neighbors nearest points (itself included).
- "range": the same test on d(p) / ||p - origin||, so that the spacing growing with range is not mistaken
  for isolation (origin: the sensor in the points' frame, one for all points or one per point, e.g. the
  per-point sensor origins of an aggregate).
- "none": keeps every point.
The build's default is "range"; "global" removes far, valid structure and keeps floaters near the sensor
(docs/measurements.md compares the methods).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.points import PointInputError
from nuplan_occ.points.knn import knn_distance_chunks

OUTLIER_METHODS = ("global", "knn", "range", "none")
MIN_RANGE_M = 1.0
"""Ranges below this are clamped in the "range" method (points on or next to the sensor)."""


def _global_mask(points: np.ndarray, k_sigma: float) -> np.ndarray:
    dist = np.linalg.norm(points - points.mean(axis=0), axis=1)
    sigma = np.sqrt(np.mean(dist**2))
    return dist < k_sigma * sigma


def _knn_mask(points: np.ndarray, nb_neighbors: int, std_ratio: float) -> np.ndarray:
    import open3d as o3d  # heavy import (~1 s), only for this non-default method

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, kept = cloud.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    keep = np.zeros(len(points), dtype=bool)
    keep[np.asarray(kept, dtype=np.int64)] = True
    return keep


def _range_mask(points: np.ndarray, origin: np.ndarray, origin_ids: np.ndarray | None, nb_neighbors: int,
                std_ratio: float) -> np.ndarray:
    k = min(nb_neighbors, len(points))
    score = np.empty(len(points))
    for rows, distances in knn_distance_chunks(points, k):  # each point's own distance 0 included, as in Open3D
        sensor = origin if origin.ndim == 1 else origin[rows if origin_ids is None else origin_ids[rows]]
        score[rows] = distances.mean(axis=1) / np.maximum(np.linalg.norm(points[rows] - sensor, axis=1), MIN_RANGE_M)
    spread = score[score > 0]  # exact duplicates do not enter the statistics (and are kept, unlike Open3D)
    if len(spread) < 2:
        return np.ones(len(points), dtype=bool)
    return score < spread.mean() + std_ratio * spread.std(ddof=1)


def remove_statistical_outliers(
    points: np.ndarray,
    method: str = "range",
    nb_neighbors: int = 8,
    std_ratio: float = 2.0,
    k_sigma: float = 3.0,
    origin: np.ndarray | None = None,
    origin_ids: np.ndarray | None = None,
) -> np.ndarray:
    """Keep mask (N,) bool of the points that are not statistical outliers.

    points (N, 3) m, any frame; origin (3,): the sensor in that frame, used by "range" only (default: the frame
    origin); (N, 3) gives each point its own sensor origin, and (F, 3) with origin_ids (N,) int gives point i
    the origin origin[origin_ids[i]] (e.g. one per sweep of an aggregate). nb_neighbors / std_ratio: the kNN
    test of "knn" and "range"; k_sigma: the "global" rule.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PointInputError(f"remove_statistical_outliers: points must be (N, 3), got shape {pts.shape}")
    if method not in OUTLIER_METHODS:
        raise PointInputError(f"remove_statistical_outliers: unknown method {method!r}; use one of {OUTLIER_METHODS}")
    if method == "none" or (len(pts) <= nb_neighbors if method != "global" else len(pts) < 2):
        return np.ones(len(pts), dtype=bool)
    if method == "global":
        return _global_mask(pts, k_sigma)
    if method == "knn":
        return _knn_mask(pts, nb_neighbors, std_ratio)
    center = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    ids = None if origin_ids is None else np.asarray(origin_ids)
    if ids is None and center.shape not in ((3,), pts.shape):
        raise PointInputError(f"remove_statistical_outliers: origin must be (3,) or {pts.shape}, got {center.shape}")
    if ids is not None and (center.ndim != 2 or center.shape[1] != 3 or ids.shape != (len(pts),)):
        raise PointInputError(f"remove_statistical_outliers: origin_ids {ids.shape} must give each of the {len(pts)} "
                             f"points a row of origin (F, 3), got origin {center.shape}")
    return _range_mask(pts, center, ids, nb_neighbors, std_ratio)
