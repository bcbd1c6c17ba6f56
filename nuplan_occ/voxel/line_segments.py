"""Points against the straight pieces of polylines in the plane: candidate pairs from a spatial index, then
distances, feet and normals by direct formulas (numba), so that a point's nearest line is found among a
handful of candidates instead of by a generic geometry query per point.

Units are those of the inputs (metres in the map's frame for nuplan-occ). A polyline's pieces are its
consecutive vertex pairs; pieces shorter than MIN_PIECE are dropped (they have no direction).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import shapely

MIN_PIECE = 1e-6
"""Pieces shorter than this are not pieces."""


@dataclass(frozen=True)
class Pieces:
    """The straight pieces of some polylines: starts, ends (S, 2); line (S,) int64 the polyline each belongs to;
    tree: a shapely STRtree over the pieces (for `candidates`)."""

    starts: np.ndarray
    ends: np.ndarray
    line: np.ndarray
    tree: shapely.STRtree

    @classmethod
    def of(cls, lines: np.ndarray) -> "Pieces":
        """Pieces of an array of shapely LineStrings (empty ones contribute none)."""
        lines = np.asarray(lines, dtype=object).reshape(-1)
        coords, which = shapely.get_coordinates(lines, return_index=True)
        same = which[1:] == which[:-1]
        starts, ends, line = coords[:-1][same], coords[1:][same], which[:-1][same]
        keep = np.hypot(*(ends - starts).T) > MIN_PIECE
        starts, ends = np.ascontiguousarray(starts[keep]), np.ascontiguousarray(ends[keep])
        return cls(starts, ends, line[keep].astype(np.int64), shapely.STRtree(shapely.linestrings(
            np.stack([starts, ends], axis=1))))

    def candidates(self, xy: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """(point index (K,), piece index (K,)): every piece within `reach` of each point xy (N, 2), sorted by
        point and then piece."""
        point_index, piece_index = self.tree.query(shapely.points(xy), predicate="dwithin", distance=reach)
        order = np.lexsort((piece_index, point_index))
        return point_index[order].astype(np.int64), piece_index[order].astype(np.int64)


@numba.njit(cache=True, inline="always")
def _foot(px, py, ax, ay, bx, by):
    """The point of the piece a -> b nearest to p: (x, y) and its distance from p."""
    dx, dy = bx - ax, by - ay
    t = min(max(((px - ax) * dx + (py - ay) * dy) / (dx * dx + dy * dy), 0.0), 1.0)
    fx, fy = ax + t * dx, ay + t * dy
    return fx, fy, np.hypot(px - fx, py - fy)


@numba.njit(cache=True)
def pair_distances(xy: np.ndarray, point_index: np.ndarray, piece_index: np.ndarray, starts: np.ndarray,
                   ends: np.ndarray) -> np.ndarray:
    """(K,) distance of point xy[point_index[k]] to piece piece_index[k]."""
    out = np.empty(len(point_index))
    for k in range(len(point_index)):
        p, s = point_index[k], piece_index[k]
        out[k] = _foot(xy[p, 0], xy[p, 1], starts[s, 0], starts[s, 1], ends[s, 0], ends[s, 1])[2]
    return out


@numba.njit(cache=True)
def nearest_pieces(xy: np.ndarray, point_index: np.ndarray, piece_index: np.ndarray, starts: np.ndarray,
                   ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point of xy (N, 2): its nearest piece among its candidate pairs (point_index sorted; the first
    of equally near ones) and the distance, -1 and inf for a point without candidates."""
    best, dist = np.full(len(xy), -1, np.int64), np.full(len(xy), np.inf)
    for k in range(len(point_index)):
        p, s = point_index[k], piece_index[k]
        d = _foot(xy[p, 0], xy[p, 1], starts[s, 0], starts[s, 1], ends[s, 0], ends[s, 1])[2]
        if d < dist[p]:
            best[p], dist[p] = s, d
    return best, dist


@numba.njit(cache=True)
def signed_offsets(xy: np.ndarray, piece_index: np.ndarray, starts: np.ndarray, ends: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """For each point xy[k] (K, 2) and piece piece_index[k]: the piece's unit normal (K, 2) (its direction
    turned left) and the point's signed distance from its foot on the piece along that normal (K,)."""
    normal, residual = np.empty((len(xy), 2)), np.empty(len(xy))
    for k in range(len(xy)):
        s = piece_index[k]
        ax, ay, bx, by = starts[s, 0], starts[s, 1], ends[s, 0], ends[s, 1]
        fx, fy, _ = _foot(xy[k, 0], xy[k, 1], ax, ay, bx, by)
        length = np.hypot(bx - ax, by - ay)
        nx, ny = -(by - ay) / length, (bx - ax) / length
        normal[k, 0], normal[k, 1] = nx, ny
        residual[k] = (xy[k, 0] - fx) * nx + (xy[k, 1] - fy) * ny
    return normal, residual
