"""BEV rasterization of map layers at a rotated pose lands in the right ego-frame cells."""

import numpy as np
import pytest
import shapely
from scipy.spatial.transform import Rotation

from nuplan_occ.geometry import make_transform, yaw_matrix
from nuplan_occ.grid import GridSpec
from nuplan_occ.io.types import MapLayer
from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE
from nuplan_occ.map_labels.bev import mark_segment_cells, rasterize_bev

GRID = GridSpec(x_min=-10, x_max=10, y_min=-10, y_max=10, z_min=-2, z_max=2, voxel_size=0.25)
YAW = np.deg2rad(60.0)
ORIGIN = np.array([500_000.0, 4_000_000.0, 10.0])  # a UTM-like global position
T_GLOBAL_FROM_EGO = make_transform(yaw_matrix(YAW), ORIGIN)
T_TILTED = make_transform(Rotation.from_euler("zyx", [YAW, np.deg2rad(3.0), np.deg2rad(-2.0)]).as_matrix(), ORIGIN)
"""A pose with pitch and roll: its cell centres map to global x, y by a 2 x 2 block that is not a rotation."""


def to_global(xy_ego, T=T_GLOBAL_FROM_EGO):
    xy = np.asarray(xy_ego, dtype=float)
    return xy @ T[:2, :2].T + T[:2, 3]


def cell(x, y):
    return int(np.floor((x - GRID.x_min) / 0.25)), int(np.floor((y - GRID.y_min) / 0.25))


def test_polygon_ahead_left_lands_at_positive_x_y_cells():
    square = shapely.Polygon(to_global([[2.0, 3.0], [6.0, 3.0], [6.0, 5.0], [2.0, 5.0]]))
    bev = rasterize_bev({"road_segments": MapLayer(np.array([square], dtype=object))}, T_GLOBAL_FROM_EGO, GRID)
    road = np.argwhere(bev == ROAD)
    assert len(road) == 16 * 8  # exactly the 4 m x 2 m square of cell centres
    assert road.min(axis=0).tolist() == list(cell(2.1, 3.1)) and road.max(axis=0).tolist() == list(cell(5.9, 4.9))
    assert np.all(bev[bev != ROAD] == OTHER_GROUND)


def test_thin_line_and_stop_polygon_become_road_line():
    line = shapely.LineString(to_global([[-8.0, -2.05], [8.0, -2.05]]))  # a painted line along ego x
    layers = {
        "road_segments": MapLayer(np.array([shapely.box(*ORIGIN[:2] - 50, *ORIGIN[:2] + 50)], dtype=object)),
        "boundaries": MapLayer(np.array([line], dtype=object)),
        "stop_polygons": MapLayer(np.array([shapely.Polygon(to_global([[3, 1], [3.3, 1], [3.3, 4], [3, 4]]))])),
    }
    bev = rasterize_bev(layers, T_GLOBAL_FROM_EGO, GRID, line_width_m=0.05)
    rows = np.unique(np.argwhere(bev[cell(-7.9, 0)[0]:cell(7.9, 0)[0] + 1, :cell(0, 0)[1]] == ROAD_LINE)[:, 1])
    assert rows.tolist() == [cell(0, -2.05)[1]]  # a 5 cm line still marks the one row of cells it crosses
    assert np.all(bev[cell(-7.9, 0)[0]:cell(7.9, 0)[0] + 1, cell(0, -2.05)[1]] == ROAD_LINE)
    assert bev[cell(3.1, 2.5)] == ROAD_LINE and bev[cell(3.2, 2.5)] == ROAD_LINE  # stop line outline
    assert bev[cell(0.0, 0.0)] == ROAD


def test_given_stop_lines_replace_the_stop_polygon_outlines():
    polygon = shapely.Polygon(to_global([[3, 1], [5, 1], [5, 4], [3, 4]]))  # 2 m deep
    layers = {
        "road_segments": MapLayer(np.array([shapely.box(*ORIGIN[:2] - 50, *ORIGIN[:2] + 50)], dtype=object)),
        "stop_polygons": MapLayer(np.array([polygon], dtype=object)),
    }
    front = shapely.LineString(to_global([[3.1, 1], [3.1, 4]]))  # the painted edge, as confirmed by paint
    only_front = rasterize_bev(layers, T_GLOBAL_FROM_EGO, GRID, stop_lines=np.array([front], dtype=object))
    assert only_front[cell(3.1, 2.5)] == ROAD_LINE
    assert only_front[cell(4.9, 2.5)] == ROAD and only_front[cell(4.0, 1.0)] == ROAD  # back and sides: road
    none = rasterize_bev(layers, T_GLOBAL_FROM_EGO, GRID, stop_lines=np.zeros(0, dtype=object))
    assert not (none == ROAD_LINE).any()
    outline = rasterize_bev(layers, T_GLOBAL_FROM_EGO, GRID)
    assert outline[cell(4.9, 2.5)] == ROAD_LINE and outline[cell(3.1, 2.5)] == ROAD_LINE


@pytest.mark.parametrize("T", [T_GLOBAL_FROM_EGO, T_TILTED], ids=["level", "tilted"])
def test_blockwise_classification_equals_cell_by_cell_reference(T):
    """Road and line cells equal the per-cell definition (centre in the road; square overlapping the strip),
    also for a road with a hole, a sliver thinner than a cell and lines crossing blocks at every angle, and for
    a pitched and rolled ego (whose squares are not squares in the global frame)."""
    rng = np.random.default_rng(3)
    ring = shapely.Polygon(to_global([[-8, -8], [8, -8], [8, 8], [-8, 8]], T),
                           [to_global([[-3, -2], [4, -3], [2, 5], [-4, 3]], T)])
    sliver = shapely.Polygon(to_global([[-9.9, 9.0], [9.9, 9.1], [9.9, 9.15], [-9.9, 9.05]], T))
    lines = [shapely.LineString(to_global(rng.uniform(-12, 12, size=(4, 2)), T)) for _ in range(6)]
    layers = {"road_segments": MapLayer(np.array([ring, sliver], dtype=object)),
              "boundaries": MapLayer(np.array(lines, dtype=object))}
    bev = rasterize_bev(layers, T, GRID, line_width_m=0.15)
    s = GRID.voxel_size
    centres = np.stack(np.meshgrid(GRID.x_min + (np.arange(80) + 0.5) * s, GRID.y_min + (np.arange(80) + 0.5) * s,
                                   indexing="ij"), axis=-1)
    road = shapely.intersects_xy(shapely.union_all([ring, sliver]), *to_global(centres.reshape(-1, 2), T).T)
    squares = shapely.polygons(to_global((centres.reshape(-1, 1, 2) + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
                                          * s / 2).reshape(-1, 2), T).reshape(-1, 4, 2))
    painted = shapely.intersects(squares, shapely.buffer(shapely.union_all(lines), 0.075, cap_style="flat"))
    expected = np.where(painted, ROAD_LINE, np.where(road, ROAD, OTHER_GROUND)).reshape(80, 80)
    assert 0 < (expected == ROAD_LINE).sum() and 0 < (expected == ROAD).sum() and 0 < (expected == OTHER_GROUND).sum()
    assert np.array_equal(bev, expected)


def test_segment_cells_are_the_closed_squares_the_segment_meets():
    """mark_segment_cells against shapely's intersects of each closed cell square with each segment, also for
    segments along a cell edge, through a corner, vertical, degenerate (a point) and reaching past the grid."""
    rng = np.random.default_rng(5)
    segments = [rng.uniform(-2, 10, size=(2, 2)) for _ in range(40)]
    segments += [np.array([[1.0, 2.0], [5.0, 2.0]]), np.array([[3.0, 1.0], [3.0, 6.5]]), np.array([[1.0, 1.0], [4.0, 4.0]]),
                 np.array([[2.5, 2.5], [2.5, 2.5]]), np.array([[7.5, 0.2], [7.5, 3.7]]), np.array([[-3.0, 4.2], [12.0, 5.1]])]
    squares = shapely.box(*np.meshgrid(np.arange(8.0), np.arange(8.0), indexing="ij"),
                          *np.meshgrid(np.arange(1.0, 9.0), np.arange(1.0, 9.0), indexing="ij"))
    for segment in segments:
        out = np.zeros((8, 8), dtype=bool)
        mark_segment_cells(segment[:1].copy(), segment[1:].copy(), out)
        line = shapely.LineString(segment) if np.any(segment[0] != segment[1]) else shapely.Point(segment[0])
        assert np.array_equal(out, shapely.intersects(squares, line)), segment
