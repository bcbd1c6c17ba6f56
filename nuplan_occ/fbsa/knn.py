"""Distances from every point of a cloud to its k nearest points of the same cloud (itself included), by a
compiled kd-tree: sliding-midpoint splits of the widest side into leaves of at most LEAF_SIZE points,
then a depth-first search per point, nearer child first, pruned by each node's bounding box.

Distances are sqrt(dx^2 + dy^2 + dz^2) in the points' frame (metres), each row sorted ascending: the
same values as `cKDTree(points).query(points, k)[0]` (which k points a tie picks does not change them).
"""

from __future__ import annotations

import math

import numba
import numpy as np

LEAF_SIZE = 24
"""Most points in a leaf of the tree."""


@numba.njit(cache=True)
def _build(points: np.ndarray, leaf_size: int):
    """(order, start, end, child, lo, hi): the points' permutation and, per node, its slice of order,
    its first child (-1 for a leaf; the second is child + 1) and its bounding box."""
    n = len(points)
    order = np.arange(n)
    cap = 2 * n + 1
    start = np.empty(cap, np.int64)
    end = np.empty(cap, np.int64)
    child = np.full(cap, -1, np.int64)
    lo = np.empty((cap, 3))
    hi = np.empty((cap, 3))
    start[0], end[0] = 0, n
    nodes = 1
    stack = np.empty(cap, np.int64)
    stack[0] = 0
    top = 1
    while top:
        top -= 1
        node = stack[top]
        s, e = start[node], end[node]
        for d in range(3):
            lo[node, d] = np.inf
            hi[node, d] = -np.inf
        for i in range(s, e):
            for d in range(3):
                v = points[order[i], d]
                lo[node, d] = min(lo[node, d], v)
                hi[node, d] = max(hi[node, d], v)
        dim = 0
        for d in range(1, 3):
            if hi[node, d] - lo[node, d] > hi[node, dim] - lo[node, dim]:
                dim = d
        if e - s <= leaf_size or hi[node, dim] == lo[node, dim]:
            continue
        mid = 0.5 * (lo[node, dim] + hi[node, dim])
        i, j = s, e - 1
        while i <= j:  # points below mid to the front; both sides keep at least one point
            if points[order[i], dim] < mid:
                i += 1
            else:
                order[i], order[j] = order[j], order[i]
                j -= 1
        child[node] = nodes
        start[nodes], end[nodes] = s, i
        start[nodes + 1], end[nodes + 1] = i, e
        stack[top] = nodes
        stack[top + 1] = nodes + 1
        top += 2
        nodes += 2
    return order, start, end, child, lo, hi


@numba.njit(cache=True)
def _box_distance2(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    total = 0.0
    for d in range(3):
        if p[d] < lo[d]:
            total += (lo[d] - p[d]) ** 2
        elif p[d] > hi[d]:
            total += (p[d] - hi[d]) ** 2
    return total


@numba.njit(cache=True)
def _search(points: np.ndarray, k: int, leaf_size: int) -> np.ndarray:
    order, start, end, child, lo, hi = _build(points, leaf_size)
    n = len(points)
    out = np.empty((n, k))
    best = np.empty(k)
    stack = np.empty(2 * n + 1, np.int64)
    stack_d2 = np.empty(2 * n + 1)  # squared distance from the point to the node's box
    for q in order:  # tree order: consecutive searches visit the same nodes
        p = points[q]
        have = 0
        stack[0], stack_d2[0] = 0, 0.0
        top = 1
        while top:
            top -= 1
            node = stack[top]
            if have == k and stack_d2[top] >= best[k - 1]:
                continue
            first = child[node]
            if first < 0:
                for i in range(start[node], end[node]):
                    r = points[order[i]]
                    d2 = (p[0] - r[0]) ** 2 + (p[1] - r[1]) ** 2 + (p[2] - r[2]) ** 2
                    if have < k or d2 < best[k - 1]:
                        slot = have if have < k else k - 1
                        while slot > 0 and best[slot - 1] > d2:  # insertion into the sorted k best
                            best[slot] = best[slot - 1]
                            slot -= 1
                        best[slot] = d2
                        have = min(have + 1, k)
                continue
            a, b = first, first + 1  # push the farther child first, so the nearer one is searched first
            da, db = _box_distance2(p, lo[a], hi[a]), _box_distance2(p, lo[b], hi[b])
            if da < db:
                a, b, da, db = b, a, db, da
            stack[top], stack_d2[top] = a, da
            stack[top + 1], stack_d2[top + 1] = b, db
            top += 2
        for j in range(k):
            out[q, j] = math.sqrt(best[j])
    return out


def knn_distances(points: np.ndarray, k: int) -> np.ndarray:
    """(N, k) ascending distances (m) from each point (N, 3) to its k nearest points, itself included;
    requires 1 <= k <= N."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if not 1 <= k <= len(pts):
        raise ValueError(f"knn_distances: need 1 <= k <= {len(pts)} points, got k = {k}")
    return _search(pts, k, LEAF_SIZE)
