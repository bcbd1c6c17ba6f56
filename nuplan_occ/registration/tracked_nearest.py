"""Nearest-neighbour correspondences of a set of points that moves a little between queries (ICP).

`TrackedNearest` answers, for each of n query points, "the nearest point of the target within `bound`"
exactly as `tree.query(x, distance_upper_bound=bound)` (nuplan_occ.points.knn.KdTree, as scipy's cKDTree)
does (same index, up to exact distance ties), but asks the tree again only for the points whose answer can
have changed since they were last asked.
Each point remembers where it was asked (`anchor`), its nearest target point there and `clear`: a radius
around the anchor inside which no other target point lies (the second-nearest distance, or the search
radius when there was none). After the point moved by delta from its anchor, every other target point is
at least clear - delta away, so the remembered nearest point is still the nearest whenever it is nearer
than that; a point that had no neighbour within `clear` has none within clear - delta. A small slack
(`TIE_SLACK_M`) keeps these decisions away from rounding ties; anything closer is asked again.
Frames: query and target points in one frame; metres.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from nuplan_occ.points.knn import KdTree

TIE_SLACK_M = 1e-9
"""Margin (m) by which a remembered answer must win a comparison to be reused without a query."""


@numba.njit(cache=True)
def _remembered(points: np.ndarray, anchor: np.ndarray, nearest: np.ndarray, clear: np.ndarray, target: np.ndarray,
                bound: float, slack: float) -> tuple[np.ndarray, np.ndarray]:
    """(distance (n,) to the remembered nearest point, inf without one; kept (n,): the remembered answer
    is still exact for points (n, 3), see the module docstring). A NaN anchor (never asked) is not kept."""
    n = len(points)
    distance = np.full(n, np.inf)
    kept = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        delta = math.sqrt((points[i, 0] - anchor[i, 0]) ** 2 + (points[i, 1] - anchor[i, 1]) ** 2
                          + (points[i, 2] - anchor[i, 2]) ** 2)
        j = nearest[i]
        if j >= 0:
            d = math.sqrt((points[i, 0] - target[j, 0]) ** 2 + (points[i, 1] - target[j, 1]) ** 2
                          + (points[i, 2] - target[j, 2]) ** 2)
            distance[i] = d
            kept[i] = d + delta + slack < clear[i] and abs(d - bound) > slack
        else:
            kept[i] = clear[i] - delta >= bound + slack
    return distance, kept


class TrackedNearest:
    """Exact nearest target point within a bound, for n query points that move between calls.

    tree: kd-tree over the target points (m, 3) (nuplan_occ.points.knn.KdTree); n: number of query points
    (the same points every call); margin_m: extra search radius of each tree query beyond the bound asked
    for, so a point can move this far before its answer expires. `queried` counts the points sent to the tree
    so far."""

    def __init__(self, tree: KdTree, n: int, margin_m: float):
        self.tree = tree
        self.margin_m = margin_m
        self.anchor = np.full((n, 3), np.nan)
        self.nearest = np.full(n, -1, dtype=np.int64)
        self.clear = np.zeros(n)
        self.queried = 0

    def query(self, points: np.ndarray, bound: float) -> np.ndarray:
        """(n,) int64 index of the nearest target point within `bound` of each of points (n, 3), -1 where
        there is none (tree.query(points, distance_upper_bound=bound) up to exact ties)."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        distance, kept = _remembered(points, self.anchor, self.nearest, self.clear, self.tree.data, bound, TIE_SLACK_M)
        ask = np.flatnonzero(~kept)
        if len(ask):
            radius = bound + self.margin_m
            d, i = self.tree.query(points[ask], k=2, distance_upper_bound=radius)
            self.anchor[ask] = points[ask]
            self.nearest[ask] = np.where(np.isfinite(d[:, 0]), i[:, 0], -1)
            self.clear[ask] = np.where(np.isfinite(d[:, 1]), d[:, 1], radius)
            distance[ask] = d[:, 0]
            self.queried += len(ask)
        return np.where(distance < bound, self.nearest, -1)
