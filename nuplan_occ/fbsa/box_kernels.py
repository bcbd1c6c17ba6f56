"""Compiled point-in-box tests (numba): one pass over the points, each trying the boxes in order and stopping
at the first that holds it, instead of numpy's points x boxes blocks.

Boxes are given by arrays only (centres, half extents, yaw cosines and sines; or 4x4 transforms), metres, in
the points' frame. Pure functions, deterministic, float64 arithmetic (the same expressions as the numpy
code they replace, so the same answers)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def first_upright_box(points: np.ndarray, centers: np.ndarray, half: np.ndarray, cos: np.ndarray, sin: np.ndarray,
                      lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) int64: the lowest index k of an upright box holding each point (N, 3), -1 if none. Box k: centre
    centers[k], half extents half[k] (box frame), yaw given by cos[k], sin[k]; lo[k], hi[k] its axis-aligned
    bounding box (a cheap first test). Faces are inclusive."""
    n, K = len(points), len(centers)
    out = np.full(n, -1, np.int64)
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for k in range(K):
            if x < lo[k, 0] or x > hi[k, 0] or y < lo[k, 1] or y > hi[k, 1] or z < lo[k, 2] or z > hi[k, 2]:
                continue
            dx, dy, dz = x - centers[k, 0], y - centers[k, 1], z - centers[k, 2]
            local_x = cos[k] * dx + sin[k] * dy
            local_y = -sin[k] * dx + cos[k] * dy
            if abs(local_x) <= half[k, 0] and abs(local_y) <= half[k, 1] and abs(dz) <= half[k, 2]:
                out[i] = k
                break
    return out


@numba.njit(cache=True)
def inside_any_frame_box(points: np.ndarray, T_box_from_points: np.ndarray, centre_distance: np.ndarray,
                         lower: np.ndarray, upper: np.ndarray, reach: float) -> np.ndarray:
    """(N,) bool: whether each point (N, 3) lies in [lower, upper) of at least one box k, given in its own
    frame by T_box_from_points[k] (K, 4, 4). The boxes must be sorted by centre_distance[k], the distance of
    box k's centre from the points' origin; reach: the farthest a point of a box lies from its centre. A
    point stops trying boxes at the first that holds it, or at the first farther than its own range plus
    reach (no later box can hold it)."""
    n, K = len(points), len(T_box_from_points)
    keep = np.zeros(n, np.bool_)
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        limit = np.sqrt(x * x + y * y + z * z) + reach
        for k in range(K):
            if centre_distance[k] > limit:
                break
            T = T_box_from_points[k]
            lx = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
            ly = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
            lz = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]
            if lower[0] <= lx < upper[0] and lower[1] <= ly < upper[1] and lower[2] <= lz < upper[2]:
                keep[i] = True
                break
    return keep


@numba.njit(cache=True)
def within_square(points: np.ndarray, center_x: float, center_y: float, half: float) -> np.ndarray:
    """(M,) int64 indices of the points (N, 3) whose x and y both lie within half of (center_x, center_y)
    (an axis-aligned square, edges inclusive; z ignored), in input order."""
    hits = np.empty(len(points), np.int64)
    m = 0
    for i in range(len(points)):
        if abs(np.float64(points[i, 0]) - center_x) <= half and abs(np.float64(points[i, 1]) - center_y) <= half:
            hits[m] = i
            m += 1
    return hits[:m]
