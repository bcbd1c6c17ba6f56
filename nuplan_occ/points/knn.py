"""k nearest points by a compiled kd-tree: sliding-midpoint splits of the widest side into leaves of at most
LEAF_SIZE points, then a depth-first search per query, nearer child first, pruned by each node's bounding
box and by the k-th best distance so far. A cloud's own points are searched one leaf at a time: the
leaf's queries share a walk pruned by box-to-box distance (`knn_distance_chunks`).

Distances are sqrt(dx^2 + dy^2 + dz^2) in the points' frame (metres), each row sorted ascending: the
same values as scipy's `cKDTree.query` (which of equally distant points a tie picks may differ, the
distances do not). `knn_distance_chunks` gives every point's distances to its k nearest points of the same
cloud (itself included); `KdTree` answers queries of other points, optionally within a bound.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numba
import numpy as np

LEAF_SIZE = 24
"""Most points in a leaf of the tree."""
LEAF_SIZE_CAP = 64
"""Rows of the per-leaf work arrays of `_self_search` (grown when a leaf holds more points: a leaf of equal
points cannot be split)."""


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
        if mid <= lo[node, dim]:  # lo and hi one float apart: the midpoint rounds onto lo, split at hi instead
            mid = hi[node, dim]
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


@numba.njit(cache=True, inline="always")
def _scan_leaf(ordered: np.ndarray, order: np.ndarray, p: np.ndarray, s: int, e: int, best: np.ndarray,
               best_index: np.ndarray, have: int, k: int, bound2: float) -> int:
    """Insert the points ordered[s:e] nearer to p than sqrt(bound2) and than the k-th best so far into the
    sorted squared distances `best` (`have` of them filled) and their indices (order[i]); the new `have`."""
    worst = best[k - 1] if have == k else bound2
    for i in range(s, e):
        r = ordered[i]
        d2 = (p[0] - r[0]) ** 2 + (p[1] - r[1]) ** 2 + (p[2] - r[2]) ** 2
        if d2 < worst:
            slot = have if have < k else k - 1
            while slot > 0 and best[slot - 1] > d2:  # insertion into the sorted k best
                best[slot] = best[slot - 1]
                best_index[slot] = best_index[slot - 1]
                slot -= 1
            best[slot] = d2
            best_index[slot] = order[i]
            have = min(have + 1, k)
            if have == k:
                worst = best[k - 1]
    return have


@numba.njit(cache=True, inline="always")
def _push_children(stack: np.ndarray, stack_d2: np.ndarray, top: int, first: int, d_first: float,
                   d_second: float) -> int:
    """Push the children first and first + 1 of a node with their squared distances, the farther one first so
    that the nearer one is walked first; the new stack top."""
    a, b, da, db = first, first + 1, d_first, d_second
    if da < db:
        a, b, da, db = b, a, db, da
    stack[top], stack_d2[top] = a, da
    stack[top + 1], stack_d2[top + 1] = b, db
    return top + 2


@numba.njit(cache=True, inline="always")
def _kth_best(best: np.ndarray, have: int, k: int) -> float:
    """The k-th best squared distance of a row with `have` filled, inf while fewer than k are."""
    return best[k - 1] if have == k else np.inf


@numba.njit(cache=True)
def search_nearest(ordered: np.ndarray, order: np.ndarray, start: np.ndarray, end: np.ndarray, child: np.ndarray,
                   lo: np.ndarray, hi: np.ndarray, queries: np.ndarray, query_order: np.ndarray, k: int, bound2: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(distances (Q, k), indices (Q, k)): the k nearest points closer than sqrt(bound2) to each query,
    ascending; inf and index len(points) where fewer lie that close. ordered = points[order] (leaves are
    contiguous slices of it); queries are searched in query_order."""
    n = len(ordered)
    distances = np.full((len(queries), k), np.inf)
    indices = np.full((len(queries), k), n, np.int64)
    best = np.empty(k)
    best_index = np.empty(k, np.int64)
    stack = np.empty(2 * n + 1, np.int64)
    stack_d2 = np.empty(2 * n + 1)  # squared distance from the query to the node's box
    for q in query_order:
        p = queries[q]
        have = 0
        worst = bound2  # a candidate must be nearer than this: the bound, then the k-th best so far
        stack[0], stack_d2[0] = 0, 0.0
        top = 1
        while top:
            top -= 1
            node = stack[top]
            if stack_d2[top] >= worst:
                continue
            first = child[node]
            if first < 0:
                have = _scan_leaf(ordered, order, p, start[node], end[node], best, best_index, have, k, bound2)
                worst = best[k - 1] if have == k else bound2
                continue
            top = _push_children(stack, stack_d2, top, first, _box_distance2(p, lo[first], hi[first]),
                                 _box_distance2(p, lo[first + 1], hi[first + 1]))
        for j in range(have):
            distances[q, j] = math.sqrt(best[j])
            indices[q, j] = best_index[j]
    return distances, indices


@numba.njit(cache=True, inline="always")
def _boxes_distance2(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray) -> float:
    total = 0.0
    for d in range(3):
        gap = max(lo_b[d] - hi_a[d], lo_a[d] - hi_b[d], 0.0)
        total += gap * gap
    return total


@numba.njit(cache=True)
def _leaves(child: np.ndarray) -> np.ndarray:
    """The tree's leaf nodes from left to right: their slices of the points' order follow one another."""
    leaves = np.empty(len(child), np.int64)
    stack = np.empty(len(child), np.int64)
    n_leaves, top = 0, 1
    stack[0] = 0
    while top:
        top -= 1
        node = stack[top]
        if child[node] < 0:
            leaves[n_leaves] = node
            n_leaves += 1
        else:
            stack[top], stack[top + 1] = child[node] + 1, child[node]
            top += 2
    return leaves[:n_leaves]


@numba.njit(cache=True)
def _self_search(ordered: np.ndarray, order: np.ndarray, start: np.ndarray, end: np.ndarray, child: np.ndarray,
                 lo: np.ndarray, hi: np.ndarray, leaves: np.ndarray, k: int) -> np.ndarray:
    """(m, k) ascending distances from each point of the given leaves (m points: ordered[start[leaves[0]]:
    end[leaves[-1]]], in that order; the leaves consecutive) to its k nearest points of the whole cloud
    (itself included), one leaf of queries at a time: each query first takes its own leaf's points, then the
    leaf's queries share one walk of the tree, pruned by box-to-box distance against the largest k-th best of
    the leaf (a query scans a leaf only when that leaf's box is nearer to it than its own k-th best). A leaf's
    rows do not depend on which other leaves are searched in the same call."""
    n = len(ordered)
    first_row = start[leaves[0]]
    distances = np.full((end[leaves[-1]] - first_row, k), np.inf)
    stack = np.empty(2 * n + 1, np.int64)
    stack_d2 = np.empty(2 * n + 1)
    best = np.empty((LEAF_SIZE_CAP, k))
    best_index = np.empty((LEAF_SIZE_CAP, k), np.int64)
    have = np.empty(LEAF_SIZE_CAP, np.int64)
    for leaf in leaves:
        s, e = start[leaf], end[leaf]
        m = e - s
        if m > best.shape[0]:
            best = np.empty((m, k))
            best_index = np.empty((m, k), np.int64)
            have = np.empty(m, np.int64)
        bound = 0.0
        for q in range(m):
            have[q] = _scan_leaf(ordered, order, ordered[s + q], s, e, best[q], best_index[q], 0, k, np.inf)
            bound = max(bound, _kth_best(best[q], have[q], k))
        stack[0], stack_d2[0] = 0, 0.0
        top = 1
        while top:
            top -= 1
            node = stack[top]
            if stack_d2[top] >= bound:
                continue
            first = child[node]
            if first < 0:
                if node == leaf:
                    continue
                bound = 0.0
                for q in range(m):
                    p = ordered[s + q]
                    if _box_distance2(p, lo[node], hi[node]) < _kth_best(best[q], have[q], k):
                        have[q] = _scan_leaf(ordered, order, p, start[node], end[node], best[q], best_index[q],
                                             have[q], k, np.inf)
                    bound = max(bound, _kth_best(best[q], have[q], k))
                continue
            top = _push_children(stack, stack_d2, top, first,
                                 _boxes_distance2(lo[leaf], hi[leaf], lo[first], hi[first]),
                                 _boxes_distance2(lo[leaf], hi[leaf], lo[first + 1], hi[first + 1]))
        for q in range(m):
            for j in range(have[q]):
                distances[s + q - first_row, j] = math.sqrt(best[q, j])
    return distances


class KdTree:
    """A kd-tree over points (n, 3) for nearest-point queries (frame of the points, metres); `data` the
    points, `n` their number (the names of scipy's cKDTree, whose query it answers the same way)."""

    def __init__(self, points: np.ndarray):
        self.data = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.n = len(self.data)
        self._nodes = _build(self.data, LEAF_SIZE)
        self._ordered = self.data[self._nodes[0]]

    @property
    def kernel_arrays(self) -> tuple[np.ndarray, ...]:
        """(ordered, order, start, end, child, lo, hi): the tree as `search_nearest` takes it, for compiled
        callers."""
        return (self._ordered, *self._nodes)

    def query(self, queries: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf
              ) -> tuple[np.ndarray, np.ndarray]:
        """(distances (Q, k), indices (Q, k)): ascending distances to the k nearest points closer than
        distance_upper_bound to each of queries (Q, 3), and their indices; inf and n where fewer are."""
        pts = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
        return search_nearest(*self.kernel_arrays, pts, np.arange(len(pts)), int(k), float(distance_upper_bound) ** 2)


CHUNK_ROWS = 1 << 18
"""Points per chunk of `knn_distance_chunks` (a chunk's distances are CHUNK_ROWS x k float64)."""


def knn_distance_chunks(points: np.ndarray, k: int, chunk_rows: int = CHUNK_ROWS
                        ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(rows (m,), distances (m, k)) chunks of about chunk_rows points that together cover every point of
    points (N, 3) once: the ascending distances (m) from points[rows] to their k nearest points of the whole
    cloud, itself included (requires 1 <= k <= N). The rows of a chunk are neighbouring leaves of one kd-tree,
    whose queries share one walk of the tree (`_self_search`); only one chunk's distances are held at a time."""
    tree = KdTree(points)
    if not 1 <= k <= tree.n:
        raise ValueError(f"knn_distance_chunks: need 1 <= k <= {tree.n} points, got k = {k}")
    order, start, end = tree._nodes[:3]
    leaves = _leaves(tree._nodes[3])
    leaf_end = end[leaves]
    first = 0
    while first < len(leaves):
        last = int(np.searchsorted(leaf_end, start[leaves[first]] + chunk_rows, side="left")) + 1
        last = min(last, len(leaves))
        chunk = leaves[first:last]
        yield order[start[chunk[0]]:end[chunk[-1]]], _self_search(tree._ordered, *tree._nodes, chunk, k)
        first = last
