"""Map-to-paint alignment against exact synthetic geometry: painted strips along known lines, a known
2D offset of the scene, curb returns that are bright but not paint, stop polygon edges painted or not."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from nuplan_occ.io.types import PointCloud
from nuplan_occ.map_labels.map_align import (GroundReturns, align_points_to_lines, flat_columns, flat_ground,
                                        ground_returns, intensity_ratio, paint_confirmed, polygon_edges)

PAINT_HALF_WIDTH = 0.075


def street_lines() -> np.ndarray:
    """Four lane lines along x, two crossing lines along y (global frame, m)."""
    along = [shapely.LineString([(-60.0, y), (60.0, y)]) for y in (-5.2, -1.7, 1.7, 5.2)]
    across = [shapely.LineString([(x, -40.0), (x, 40.0)]) for x in (-20.0, 25.0)]
    return np.array(along + across, dtype=object)


def strip_points(lines: np.ndarray, per_line: int, rng: np.random.Generator, offset_m: float = 0.0) -> np.ndarray:
    """(N, 2) points uniformly on the painted strips of `lines` (shifted sideways by offset_m)."""
    out = []
    for line in lines:
        s = rng.uniform(0.0, line.length, per_line)
        on = shapely.get_coordinates(shapely.line_interpolate_point(line, s))
        a, b = np.asarray(line.coords)[[0, -1]]
        tangent = (b - a) / np.linalg.norm(b - a)
        normal = np.array([-tangent[1], tangent[0]])
        out.append(on + normal * (offset_m + rng.uniform(-PAINT_HALF_WIDTH, PAINT_HALF_WIDTH, (per_line, 1))))
    return np.vstack(out)


def misplace(points_true: np.ndarray, dx: float, dy: float, dyaw: float) -> np.ndarray:
    """The points as a scene whose pose is off: observed = R(dyaw)^T (true - (dx, dy))."""
    c, s = np.cos(dyaw), np.sin(dyaw)
    return (points_true - [dx, dy]) @ np.array([[c, -s], [s, c]])


def apply(correction: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ correction[:2, :2].T + correction[:2, 3]


def test_recovers_a_known_offset_despite_bright_curb_returns():
    rng = np.random.default_rng(0)
    lines = street_lines()
    paint = strip_points(lines, 600, rng)
    # bright curb returns 0.3 m outside the two edge lines, as many as on those lines: least squares on the
    # nearest line would be pulled 0.15 m toward them
    curb = strip_points(lines[[0, 3]], 600, rng, offset_m=0.3) * [1.0, 1.0]
    curb[:600, 1] -= 0.6  # the lower edge line's curb lies below it
    clutter = rng.uniform(-50.0, 50.0, (300, 2))
    truth = np.vstack([paint, curb, clutter])
    observed = misplace(truth, 0.12, -0.07, np.radians(0.08))

    result = align_points_to_lines(observed, lines)

    assert result.applied and result.reason == ""
    error = np.linalg.norm(apply(result.correction, observed) - truth, axis=1)
    assert error.max() < 0.01
    assert result.rms_after < result.rms_before


def test_direction_the_lines_do_not_constrain_stays_at_zero():
    rng = np.random.default_rng(1)
    lines = street_lines()[:4]  # all along x: an offset along x is invisible
    truth = strip_points(lines, 500, rng)
    observed = misplace(truth, 0.3, 0.05, 0.0)

    result = align_points_to_lines(observed, lines)

    moved = apply(result.correction, observed)
    assert np.abs(moved[:, 1] - truth[:, 1]).max() < 0.01  # across the lines: corrected
    assert np.abs(moved[:, 0] - observed[:, 0]).max() < 0.01  # along them: left alone, not guessed


def test_refuses_without_enough_paint_and_beyond_the_allowed_offset():
    rng = np.random.default_rng(2)
    lines = street_lines()
    few = align_points_to_lines(strip_points(lines, 20, rng), lines)
    assert not few.applied and "paint points" in few.reason
    assert np.array_equal(few.correction, np.eye(4))

    observed = misplace(strip_points(lines, 500, rng), 0.4, 0.3, 0.0)
    far = align_points_to_lines(observed, lines, max_offset_m=0.2)
    assert np.hypot(far.dx, far.dy) <= 0.2 + 1e-9  # never a move beyond the allowed offset

    turned = misplace(strip_points(lines, 500, rng), 0.0, 0.0, np.radians(0.3))
    assert align_points_to_lines(turned, lines).applied
    refused = align_points_to_lines(turned, lines, max_yaw_deg=0.1)
    assert not refused.applied and "deg" in refused.reason
    assert np.array_equal(refused.correction, np.eye(4))


def test_flat_ground_leaves_out_columns_at_a_curb():
    x, y = np.meshgrid(np.arange(-5.0, 5.0, 0.1), np.arange(-2.0, 2.0, 0.1), indexing="ij")
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    z = np.where(xy[:, 0] >= 1.0, 0.15, 0.0)  # a walkway raised 0.15 m from x = 1 m on
    points = np.column_stack([xy, z])
    flat = flat_ground(points)
    assert flat[np.abs(xy[:, 0] - 1.0) > 1.0].all()  # more than a cell and its neighbours away: flat
    assert not flat[np.abs(xy[:, 0] - 1.0) < 0.1].any()  # at the curb: not flat


def test_flatness_is_judged_over_all_sweeps_together_one_sweep_at_a_time():
    """Sweep 0 sees only flat road; sweep 1, from 10 m further on, also sees a 0.15 m curb at global x = 12 m.
    The road returns of sweep 0 next to the curb are not flat ground; the same merged cloud decides as when
    the sweeps are merged first."""
    x, y = np.meshgrid(np.arange(5.0, 15.0, 0.1), np.arange(-2.0, 2.0, 0.1), indexing="ij")
    road = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    curb = road[np.abs(road[:, 0] - 12.0) < 0.3] + [0.0, 0.0, 0.15]
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, 0, 3] = 10.0
    sweeps_ego = [road, np.vstack([road, curb]) - [10.0, 0.0, 0.0]]
    placed = [sweeps_ego[0], sweeps_ego[1] + [10.0, 0.0, 0.0]]
    columns = flat_columns(placed)
    near_curb = np.abs(road[:, 0] - 12.0) < 0.5
    flat0 = columns.of(placed[0])
    assert not flat0[near_curb].any() and flat0[np.abs(road[:, 0] - 12.0) > 1.0].all()
    assert flat_ground(placed[0]).all()  # alone, sweep 0 is flat everywhere
    np.testing.assert_array_equal(np.concatenate([columns.of(p) for p in placed]), flat_ground(np.vstack(placed)))
    clouds = [PointCloud(p, np.full(len(p), 10.0), np.zeros(len(p), np.int16), np.zeros(len(p), np.int8), "ego")
              for p in sweeps_ego]
    returns = ground_returns(clouds, T, np.array([0.0, 0.0, 1.9]))
    assert len(returns.xy) == int(np.concatenate([columns.of(p) for p in placed]).sum())
    assert not np.any(np.abs(returns.xy[:, 0] - 12.0) < 0.5)


def test_intensity_ratio_compares_with_the_ground_at_the_same_range():
    rng = np.random.default_rng(3)
    r = rng.uniform(5.0, 30.0, 5000)
    phi = rng.uniform(-np.pi, np.pi, 5000)
    points = np.column_stack([r * np.cos(phi), r * np.sin(phi), np.zeros(5000)])
    paint = rng.random(5000) < 0.1
    intensity = np.where(paint, 8.0, 1.0) * 100.0 / r  # falls with range; paint 8 times brighter
    ratio = intensity_ratio(points, intensity, np.zeros(3))
    assert np.allclose(ratio[paint], 8.0, rtol=0.2)
    assert np.allclose(ratio[~paint], 1.0, rtol=0.2)


def test_intensity_ratio_divides_by_each_range_bins_median_and_leaves_thin_or_dark_bins_nan():
    """Known medians per 2 m bin of flat ground: an even count (mean of the middle two), an odd count, a bin
    below min_per_bin and a bin whose median is zero; points off the flat ground take their bin's median."""
    rng = np.random.default_rng(5)
    ranges = np.concatenate([np.full(40, 10.5), np.full(41, 12.5), np.full(10, 14.5), np.full(30, 16.5)])
    phi = rng.uniform(-0.3, 0.3, len(ranges))
    points = np.column_stack([ranges * np.cos(phi), ranges * np.sin(phi), np.zeros(len(ranges))])
    intensity = np.concatenate([rng.permutation(np.arange(40.0)), rng.permutation(np.arange(41.0) * 2),
                                np.full(10, 5.0), np.zeros(30)])
    ratio = intensity_ratio(points, intensity, np.zeros(3), range_bin_m=2.0, min_per_bin=20)
    np.testing.assert_array_equal(ratio[:40], intensity[:40] / 19.5)
    np.testing.assert_array_equal(ratio[40:81], intensity[40:81] / 40.0)
    assert np.isnan(ratio[81:]).all()


def test_ground_returns_keep_paint_and_drop_the_bright_curb():
    rng = np.random.default_rng(4)
    xy = rng.uniform([-20.0, -10.0], [20.0, 10.0], (40000, 2))
    on_walkway = xy[:, 1] > 6.0
    z = np.where(on_walkway, 0.15, 0.0)
    painted = np.abs(xy[:, 1] - 1.7) <= PAINT_HALF_WIDTH
    curb = np.abs(xy[:, 1] - 6.0) < 0.15
    intensity = np.where(painted | curb, 50.0, 10.0)
    T = np.eye(4)
    T[:2, 3] = [100.0, 200.0]
    cloud = PointCloud(np.column_stack([xy, z]), intensity, np.zeros(len(xy), np.int16), np.zeros(len(xy), np.int8), "ego")
    returns = ground_returns([cloud], T[None], np.array([0.0, 0.0, 1.9]))
    bright_y = returns.xy[returns.bright, 1] - 200.0
    assert len(bright_y) > 100 and np.all(np.abs(bright_y - 1.7) <= PAINT_HALF_WIDTH + 1e-9)


def test_stop_polygon_edges_are_painted_only_where_the_returns_show_paint():
    polygon = shapely.box(10.0, 0.0, 12.0, 3.5)  # 2 m deep; its edge at x = 10 is painted
    edges = polygon_edges(np.array([polygon], dtype=object))
    assert len(edges) == 4
    rng = np.random.default_rng(5)
    xy = rng.uniform([5.0, -1.0], [15.0, 5.0], (20000, 2))
    bright = np.abs(xy[:, 0] - 10.0) <= PAINT_HALF_WIDTH
    confirmed = paint_confirmed(edges, GroundReturns(xy, bright), width_m=0.15)
    painted_edge = [bool(np.allclose(shapely.get_coordinates(e)[:, 0], 10.0)) for e in edges]
    assert confirmed.tolist() == painted_edge

    unobserved = GroundReturns(xy[xy[:, 0] < 9.0], bright[xy[:, 0] < 9.0])
    assert not paint_confirmed(edges, unobserved, width_m=0.15).any()


@pytest.mark.parametrize("polygons", [np.zeros(0, dtype=object)])
def test_no_stop_polygons_no_edges(polygons):
    assert len(polygon_edges(polygons)) == 0
