"""Compiled point-in-box tests (numba): one pass over the points, each trying the boxes in order (upright boxes:
only those listed for the point's x-y cell) and stopping at the first that holds it, instead of numpy's
points x boxes blocks.

Boxes are given by arrays only (centres, half extents, yaw cosines and sines; or 4x4 transforms), metres, in
the points' frame. Pure functions, deterministic, float64 arithmetic (the same expressions as the numpy
code they replace, so the same answers)."""

from __future__ import annotations

import numba
import numpy as np


BUCKET_CELL_M = 4.0
"""Edge (m) of the x-y cells by which `first_upright_box` lists the boxes a point may lie in."""
MAX_BUCKET_CELLS = 1 << 20
"""Most x-y cells of that list: boxes spread wider get proportionally larger cells."""


@numba.njit(cache=True)
def _box_buckets(lo: np.ndarray, hi: np.ndarray, cell: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """(origin (2,), cells (2,), start (C + 1,), boxes, cell edge used): the x-y cells of edge `cell` (doubled
    until at most MAX_BUCKET_CELLS cover the boxes) and, as CSR (cell c's boxes are boxes[start[c]:start[c +
    1]]), in ascending order, the boxes whose finite bounding rectangle [lo, hi] meets each cell."""
    origin = np.array([lo[:, 0].min(), lo[:, 1].min()])
    extent = np.array([hi[:, 0].max() - origin[0], hi[:, 1].max() - origin[1]])
    while (np.floor(extent[0] / cell) + 1) * (np.floor(extent[1] / cell) + 1) > MAX_BUCKET_CELLS:
        cell *= 2.0
    cells = np.array([int(extent[0] / cell) + 1, int(extent[1] / cell) + 1])
    first = np.empty((len(lo), 2), np.int64)
    last = np.empty((len(lo), 2), np.int64)
    start = np.zeros(cells[0] * cells[1] + 1, np.int64)
    for k in range(len(lo)):
        for a in range(2):
            first[k, a] = int(np.floor((lo[k, a] - origin[a]) / cell))
            last[k, a] = min(int(np.floor((hi[k, a] - origin[a]) / cell)), cells[a] - 1)
        for cx in range(first[k, 0], last[k, 0] + 1):
            for cy in range(first[k, 1], last[k, 1] + 1):
                start[cx * cells[1] + cy + 1] += 1
    for c in range(len(start) - 1):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    boxes = np.empty(start[-1], np.int64)
    for k in range(len(lo)):  # ascending k: each cell's list is in box order
        for cx in range(first[k, 0], last[k, 0] + 1):
            for cy in range(first[k, 1], last[k, 1] + 1):
                boxes[fill[cx * cells[1] + cy]] = k
                fill[cx * cells[1] + cy] += 1
    return origin, cells, start, boxes, cell


@numba.njit(cache=True)
def first_upright_box(points: np.ndarray, centers: np.ndarray, half: np.ndarray, cos: np.ndarray, sin: np.ndarray,
                      lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) int64: the lowest index k of an upright box holding each point (N, 3), -1 if none. Box k: centre
    centers[k], half extents half[k] (box frame), yaw given by cos[k], sin[k]; lo[k], hi[k] its axis-aligned
    bounding box (a cheap first test). Faces are inclusive. A point tries only the boxes listed for its x-y
    cell of BUCKET_CELL_M (`_box_buckets`: every box whose bounding rectangle meets the cell), in order."""
    n, K = len(points), len(centers)
    out = np.full(n, -1, np.int64)
    if K == 0:
        return out
    bucketed = np.isfinite(lo).all() and np.isfinite(hi).all()
    if bucketed:
        origin, cells, start, boxes, cell = _box_buckets(lo, hi, BUCKET_CELL_M)
    else:  # a box without a finite rectangle: every point tries every box
        origin, cells, start, boxes, cell = np.zeros(2), np.ones(2, np.int64), np.array([0, K]), np.arange(K), 1.0
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        c = 0
        if bucketed:
            u, v = (x - origin[0]) / cell, (y - origin[1]) / cell
            if not (u >= 0.0 and v >= 0.0 and u < cells[0] and v < cells[1]):
                continue
            c = int(u) * cells[1] + int(v)
        for m in range(start[c], start[c + 1]):
            k = boxes[m]
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
