"""Points against polyline pieces, on lines with exact geometry."""

from __future__ import annotations

import numpy as np
import shapely

from nuplan_occ.map_labels.line_segments import NearPieces, Pieces, nearest_pieces, pair_distances, signed_offsets


def l_shape() -> np.ndarray:
    """An L (0, 0) -> (10, 0) -> (10, 10) with a repeated vertex, a segment along y at x = -5, and an empty line."""
    return np.array([shapely.LineString([(0, 0), (10, 0), (10, 0), (10, 10)]),
                     shapely.LineString([(-5, -5), (-5, 5)]), shapely.LineString()], dtype=object)


def test_pieces_are_consecutive_vertex_pairs_of_each_line_without_empty_ones():
    pieces = Pieces.of(l_shape())

    assert np.array_equal(pieces.starts, [[0, 0], [10, 0], [-5, -5]])
    assert np.array_equal(pieces.ends, [[10, 0], [10, 10], [-5, 5]])
    assert np.array_equal(pieces.line, [0, 0, 1])


def test_nearest_piece_distance_and_signed_offset():
    pieces = Pieces.of(l_shape())
    xy = np.array([[4.0, 0.3], [12.0, 5.0], [-5.5, 0.0], [13.0, -4.0], [30.0, 30.0]])
    point_index, piece_index = pieces.candidates(xy, 6.0)

    best, dist = nearest_pieces(xy, point_index, piece_index, pieces.starts, pieces.ends)

    assert np.array_equal(best, [0, 1, 2, 0, -1])  # (13, -4) is 5 m from the corner, the first piece's end
    assert np.allclose(dist[:4], [0.3, 2.0, 0.5, 5.0]) and dist[4] == np.inf
    normal, residual = signed_offsets(xy[:3], best[:3], pieces.starts, pieces.ends)
    assert np.allclose(normal, [[0, 1], [-1, 0], [-1, 0]])  # each piece's direction turned left
    assert np.allclose(residual, [0.3, -2.0, 0.5])
    assert np.allclose(pair_distances(xy, point_index, piece_index, pieces.starts, pieces.ends),
                       [shapely.distance(shapely.LineString([pieces.starts[s], pieces.ends[s]]), shapely.Point(xy[p]))
                        for p, s in zip(point_index, piece_index)])


def test_pairs_keep_each_lines_nearest_piece_and_nearest_stays_exact_after_a_long_move():
    pieces = Pieces.of(l_shape())
    xy = np.array([[9.5, 0.4], [-4.0, 0.0]])
    near = NearPieces(pieces, xy, radius=1.5, gate_m=0.5, slack_m=1.0)

    point_index, piece_index = near.pairs(1.2)

    assert np.array_equal(point_index, [0, 1]) and np.array_equal(piece_index, [0, 2])  # one pair per line: its nearest piece
    moved = xy + [[0.0, 20.0], [-1.0, 0.0]]  # the first point went 20 m up, beyond the indexed radius
    best, dist = near.nearest(moved)
    assert np.array_equal(best, [-1, 2]) and np.allclose(dist[1], 0.0)
    best, dist = near.nearest(xy + [[0.3, 5.0], [0.0, 0.0]])
    assert np.array_equal(best, [1, 2]) and np.allclose(dist, [0.2, 1.0])
