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


class NearPieces:
    """The line pieces near some points as they move: candidate pairs within `radius` of the points where they
    were last indexed, queried again for points that have moved so far that a piece within the gate could
    be missing."""

    def __init__(self, pieces: Pieces, xy: np.ndarray, radius: float, gate_m: float, slack_m: float):
        """xy (N, 2) the points; radius: the first lookup's; gate_m: `nearest` is exact within it; slack_m: a
        second lookup reaches this far beyond the gate."""
        self.pieces, self.gate_m, self.slack_m = pieces, gate_m, slack_m
        self._index(xy, radius)

    def _index(self, xy: np.ndarray, radius: float) -> None:
        self.xy, self.radius = xy, radius
        self.point_index, self.piece_index = self.pieces.candidates(xy, radius)

    def pairs(self, reach_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(point index, piece index): for every point and every line within reach_m of it (<= the indexed
        radius), the line's nearest piece (the first of equally near ones), sorted by point."""
        if reach_m > self.radius:
            raise ValueError(f"pairs within {reach_m} m of points indexed within {self.radius} m")
        p = self.pieces
        dist = pair_distances(self.xy, self.point_index, self.piece_index, p.starts, p.ends)
        near = dist <= reach_m
        point_index, piece_index, dist = self.point_index[near], self.piece_index[near], dist[near]
        order = np.lexsort((piece_index, dist, p.line[piece_index], point_index))
        point_index, piece_index = point_index[order], piece_index[order]
        line = p.line[piece_index]
        first = np.r_[True, (point_index[1:] != point_index[:-1]) | (line[1:] != line[:-1])]
        return point_index[first], piece_index[first]

    def nearest(self, moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per point (its position `moved` (N, 2)): the nearest piece and its distance, exact within the gate
        (-1 and inf where no piece is within the indexed radius)."""
        motion = float(np.max(np.hypot(*(moved - self.xy).T))) if len(moved) else 0.0
        if self.gate_m + motion > self.radius:
            self._index(moved, self.gate_m + self.slack_m)
        p = self.pieces
        return nearest_pieces(moved, self.point_index, self.piece_index, p.starts, p.ends)
