"""Space carving of an analytic L-shaped object (box frame) seen from several sensor origins."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.carve import carve_object_solid, cells_holding_points, lattice_shape, segments_through_box

SIZE = np.array([2.0, 1.0, 1.0])
# the L: a full-length slab below z = 0.03 and a block behind x = 0.03 (faces inside lattice cells, not on
# cell boundaries, so every cell is either inside, outside or crossed by a face)
PARTS = [(np.array([-1.0, -0.5, -0.5]), np.array([1.0, 0.5, 0.03])),
         (np.array([-1.0, -0.5, -0.5]), np.array([0.03, 0.5, 0.5]))]


def _first_hits(origin: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Points where rays origin -> target (extended 3x) first enter the L (rays that miss it are dropped)."""
    d = (targets - origin) * 3.0
    best = np.full(len(d), np.inf)
    for lo, hi in PARTS:
        with np.errstate(divide="ignore"):
            ta, tb = (lo - origin) / d, (hi - origin) / d
        enter, leave = np.minimum(ta, tb).max(axis=1), np.maximum(ta, tb).min(axis=1)
        hit = (enter <= leave) & (enter >= 0) & (enter <= 1)
        best = np.where(hit, np.minimum(best, enter), best)
    ok = np.isfinite(best)
    return origin + best[ok, None] * d[ok]


def _observations(origins: list[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    targets = rng.uniform(-SIZE / 2, SIZE / 2, size=(20_000, 3))
    points, sensors = [], []
    for origin in np.array(origins, dtype=np.float64):
        hits = _first_hits(origin, targets)
        points.append(hits)
        sensors.append(np.repeat(origin[None], len(hits), axis=0))
    return np.vstack(points), np.vstack(sensors)


def _cells_touching_l(resolution: float) -> set:
    counts, edge = lattice_shape(SIZE, resolution)
    ijk = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    lo = ijk * edge - SIZE / 2
    hi = lo + edge
    touch = np.zeros(len(ijk), bool)
    for plo, phi in PARTS:
        touch |= np.all((lo < phi) & (hi > plo), axis=1)
    return {tuple(c) for c in np.round(((lo + hi) / 2)[touch], 6)}


def test_carving_recovers_the_l_shape_seen_from_around():
    origins = [(6.0, 0.0, 0.3), (0.5, 0.0, 6.0), (0.5, 6.0, 0.3), (0.5, -6.0, 0.3), (5.0, 3.0, 4.0)]
    points, sensors = _observations(origins)
    solid = carve_object_solid(points, sensors, SIZE, resolution=0.1)
    got = {tuple(c) for c in np.round(solid, 6)}
    assert got == _cells_touching_l(0.1)


def test_unobserved_space_stays_solid():
    # seen only from behind, the object shows its full-height back face: nothing inside the box is carved
    points, sensors = _observations([(-6.0, 0.0, 0.3)])
    assert len(points) > 1000
    solid = carve_object_solid(points, sensors, SIZE, resolution=0.1)
    assert len(solid) == int(np.prod(lattice_shape(SIZE, 0.1)[0]))
    # seen only from the front at the height of the notch, the notch is carved, the space behind the
    # block's front face (which no ray reaches) is solid although no point lies there
    points, sensors = _observations([(6.0, 0.0, 0.3)])
    solid = carve_object_solid(points, sensors, SIZE, resolution=0.1)
    assert np.any((solid[:, 0] < -0.5) & (solid[:, 2] > 0.2))
    assert not np.any((solid[:, 0] > 0.1) & (solid[:, 2] > 0.1) & (np.abs(solid[:, 1]) < 0.3))


def test_rays_through_the_box_carve_away_from_its_faces():
    # seen only from behind nothing is carved; background rays crossing the notch along y at z = 0.25 carve
    # the notch cells on their line, but not within through_margin_m of the box faces (|y| > 0.38 and the
    # ray at x = 0.95 > 0.88 do not carve)
    points, sensors = _observations([(-6.0, 0.0, 0.3)])
    x = np.arange(0.15, 1.0, 0.1)
    starts = np.stack([x, np.full_like(x, -6.0), np.full_like(x, 0.25)], 1)
    ends = starts * [1.0, -1.0, 1.0]
    solid = carve_object_solid(points, sensors, SIZE, resolution=0.1, through=(starts, ends), through_margin_m=0.12)
    full = int(np.prod(lattice_shape(SIZE, 0.1)[0]))
    carved = full - len(solid)
    assert carved == 8 * 8  # x cells 0.15 .. 0.85, y cells -0.35 .. 0.35
    on_line = (solid[:, 0] > 0.1) & (solid[:, 0] < 0.9) & np.isclose(solid[:, 2], 0.25)
    assert set(np.round(solid[on_line, 1], 6)) == {-0.45, 0.45}


def test_segments_through_a_yawed_box():
    center, yaw, size = np.array([10.0, 5.0, 1.0]), np.pi / 2, np.array([4.0, 2.0, 2.0])
    starts = np.array([[10.0, 0.0, 1.0], [12.0, 0.0, 1.0], [10.0, 0.0, 3.5]])  # along the box, beside it, above
    ends = starts + [0.0, 20.0, 0.0]
    starts_box, ends_box = segments_through_box(starts, ends, center, yaw, size)
    assert len(starts_box) == 1
    assert np.allclose(starts_box[0], [-5.0, 0.0, 0.0]) and np.allclose(ends_box[0], [15.0, 0.0, 0.0])


def test_segments_through_box_picks_every_crossing_among_many():
    """The compiled cull only preselects: the crossings are exactly those of the slab test on all segments,
    including segments grazing a face, running inside a face's plane and starting inside the box."""
    from nuplan_occ.aggregation.box_cull import segments_near_box
    from nuplan_occ.aggregation.carve import clip_segments_to_box

    rng = np.random.default_rng(4)
    center, yaw, size = np.array([8.0, -3.0, 0.5]), 0.7, np.array([4.5, 1.9, 1.6])
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    ends = rng.uniform(-20, 30, (20000, 3))
    starts = np.where(rng.random((20000, 1)) < 0.9, [1.5, 0.0, 1.6], rng.uniform(-20, 30, (20000, 3)))
    grazing_box = np.array([[2.25, 0.95, -2.0], [2.25, 0.95, 2.0], [-3.0, 0.95, 0.0], [3.0, 0.95, 0.0],
                            [0.0, 0.0, 0.0], [0.0, 0.0, 0.1]])  # along an edge, along a face, inside
    grazing = (grazing_box @ R) + center
    starts, ends = np.vstack([starts, grazing[::2]]), np.vstack([ends, grazing[1::2]])
    starts_box, ends_box = (starts - center) @ R.T, (ends - center) @ R.T
    t0, t1 = clip_segments_to_box(starts_box, ends_box, size / 2)
    crossing = t0 < t1
    assert segments_near_box(starts, ends, center, yaw, size / 2, 1e-6)[crossing].all()
    got_starts, got_ends = segments_through_box(starts, ends, center, yaw, size)
    assert 100 < len(got_starts) == crossing.sum() and crossing[-1]  # the segment inside the box
    np.testing.assert_allclose(got_starts, starts_box[crossing], atol=1e-12)
    np.testing.assert_allclose(got_ends, ends_box[crossing], atol=1e-12)


def test_lattice_tiles_the_box_and_inputs_are_checked():
    counts, edge = lattice_shape(np.array([4.5, 1.9, 1.55]), 0.1)
    assert counts.tolist() == [45, 19, 16] and np.all(edge <= 0.1) and np.allclose(counts * edge, [4.5, 1.9, 1.55])
    with pytest.raises(PointInputError, match="origins_box"):
        carve_object_solid(np.zeros((3, 3)), np.zeros((2, 3)), SIZE)
    with pytest.raises(PointInputError, match="size"):
        carve_object_solid(np.zeros((3, 3)), np.zeros((3, 3)), np.array([1.0, 0.0, 1.0]))
    assert len(carve_object_solid(np.zeros((0, 3)), np.zeros((0, 3)), SIZE, resolution=0.5)) == 4 * 2 * 2


def test_cell_corner_points_reach_the_cells_corners():
    from nuplan_occ.aggregation.carve import cell_corner_points, lattice_shape

    size = np.array([0.4, 0.3, 0.2])
    counts, edge = lattice_shape(size, 0.1)
    cells = np.array([[-0.15, -0.1, -0.05], [0.15, 0.1, 0.05]])
    points = cell_corner_points(cells, size, 0.1, inset=0.05)
    assert points.shape == (16, 3)
    np.testing.assert_allclose(points[:8].min(axis=0), cells[0] - 0.45 * edge)
    np.testing.assert_allclose(points[8:].max(axis=0), cells[1] + 0.45 * edge)
    # every corner point stays in its own cell
    ijk = np.floor((points + size / 2) / edge).astype(int)
    assert np.array_equal(ijk[:8], np.repeat([[0, 0, 0]], 8, axis=0)) and np.array_equal(ijk[8:], np.repeat([[3, 2, 1]], 8, axis=0))


def test_cells_holding_points_marks_exactly_the_observed_cells():
    size = np.array([1.0, 0.6, 0.4])
    counts, edge = lattice_shape(size, 0.1)
    ijk = np.stack(np.unravel_index(np.arange(int(np.prod(counts))), tuple(counts)), axis=1)
    cells = (ijk + 0.5) * edge - size / 2
    points = np.array([[0.43, 0.21, -0.17], [-0.05, 0.0, 0.0], [3.0, 0.0, 0.0]])  # the last one is outside
    held = cells_holding_points(cells, points, size, 0.1)
    assert held.sum() == 2
    for point in points[:2]:  # each inside point is in one of the two marked cells
        assert (np.abs(cells[held] - point).max(axis=1) <= edge.max() / 2 + 1e-9).sum() == 1


def test_solid_samples_are_cell_centres_or_their_corners_with_the_observed_cells_marked():
    from nuplan_occ.aggregation.carve import object_solid_samples

    size = np.array([1.0, 1.0, 1.0])
    point = np.array([[-0.43, 0.45, 0.45]])  # in the cell x [-0.5, -0.4], y, z [0.4, 0.5]; seen from far along +x
    origin = np.array([[5.0, 0.45, 0.45]])
    centres = object_solid_samples(point, origin, size, 0.1, None, corners=False)
    corners = object_solid_samples(point, origin, size, 0.1, None, corners=True)
    # the ray carves the 9 cells of its row in front of the point's cell (it stops 0.05 m short of the point)
    assert len(centres.points) == 1000 - 9 and centres.observed.sum() == 1
    np.testing.assert_allclose(centres.points[centres.observed], [[-0.45, 0.45, 0.45]])
    assert corners.points.shape == (8 * len(centres.points), 3) and corners.observed.sum() == 8
    np.testing.assert_allclose(np.abs(corners.points[corners.observed] - [-0.45, 0.45, 0.45]), 0.045)


def test_the_top_envelope_removes_the_unseen_air_above_a_truck_bed_and_keeps_unknown_columns():
    """A 6 x 2 x 2.5 m box holding a truck: a cab (x < 0) 2.5 m tall and a bed (x >= 0) 1.2 m tall, seen only on
    its left side (y = +1) and the bed's floor; the right half is never seen. Over the bed the solid ends 0.1 m
    above the bed; the cab's cells stay; columns with only ground returns keep their cells."""
    from nuplan_occ.aggregation.carve import lattice_shape, under_top_envelope

    size = np.array([6.0, 2.0, 2.5])
    rng = np.random.default_rng(0)
    cab = np.column_stack([rng.uniform(-3, 0, 3000), np.full(3000, 1.0), rng.uniform(-0.9, 1.25, 3000)])
    bed_side = np.column_stack([rng.uniform(0, 3, 2000), np.full(2000, 1.0), rng.uniform(-0.9, -0.05, 2000)])
    bed_floor = np.column_stack([rng.uniform(0, 3, 2000), rng.uniform(-1, 1, 2000), np.full(2000, -0.05)])
    ground = np.column_stack([rng.uniform(-3, 3, 500), np.full(500, -0.95), np.full(500, -1.24)])
    points = np.vstack([cab, bed_side, bed_floor, ground])
    counts, edge = lattice_shape(size, 0.1)
    ijk = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), axis=-1).reshape(-1, 3)
    cells = (ijk + 0.5) * edge - size / 2
    keep = under_top_envelope(cells, points, size, 0.1, reach_m=0.3, pad_m=0.1, floor_clearance_m=0.3)
    bed = (cells[:, 0] > 0.5) & (cells[:, 1] > 0.5)
    assert not keep[bed & (cells[:, 2] - edge[2] / 2 > 0.05 + 1e-9)].any()
    assert keep[bed & (cells[:, 2] < -0.1)].all()
    assert keep[(cells[:, 0] < -0.5) & (cells[:, 1] > 0.5)].all()  # the cab, up to its top
    assert keep[(np.abs(cells[:, 1] + 0.95) < 0.05) & (cells[:, 0] < -0.5)].all()  # ground returns only: kept


def test_an_unseen_hood_top_ends_where_its_seen_side_does_across_the_width():
    """A 4.5 x 1.8 x 1.5 m car box: its cabin (|x| < 1) seen on the left side up to the roof (0.75), its hood
    (x > 1.2) seen on the left side up to the belt (0.05), the hood's top and the trunk (x < -1.5) never seen.
    The hood's inside columns, beyond the envelope's reach of the side, take the side's top across the width;
    the unseen trunk keeps its box, and without across_width the hood keeps it too."""
    from nuplan_occ.aggregation.carve import lattice_shape, under_top_envelope

    size = np.array([4.5, 1.8, 1.5])
    rng = np.random.default_rng(1)
    cabin = np.column_stack([rng.uniform(-1, 1, 3000), np.full(3000, 0.85), rng.uniform(-0.4, 0.75, 3000)])
    hood = np.column_stack([rng.uniform(1.2, 2.25, 2000), np.full(2000, 0.85), rng.uniform(-0.4, 0.05, 2000)])
    points = np.vstack([cabin, hood])
    counts, edge = lattice_shape(size, 0.1)
    ijk = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), axis=-1).reshape(-1, 3)
    cells = (ijk + 0.5) * edge - size / 2
    across = under_top_envelope(cells, points, size, 0.1, reach_m=0.3, pad_m=0.1, floor_clearance_m=0.3,
                                across_width=True)
    column_only = under_top_envelope(cells, points, size, 0.1, reach_m=0.3, pad_m=0.1, floor_clearance_m=0.3)
    inside_hood = (cells[:, 0] > 1.6) & (cells[:, 1] < 0.4)
    above_belt = cells[:, 2] - edge[2] / 2 > hood[:, 2].max() + 0.1
    assert not across[inside_hood & above_belt].any() and across[inside_hood & ~above_belt].all()
    assert column_only[inside_hood].all()
    trunk = cells[:, 0] < -1.9
    assert across[trunk].all() and column_only[trunk].all()
    assert across[(np.abs(cells[:, 0]) < 0.6)].all()  # the cabin's whole cross-section, up to its roof


def test_an_end_seen_nowhere_takes_a_low_top_of_the_seen_columns():
    """A 7.4 x 2.3 x 2.9 m truck box seen only from behind and above its rear: its bed (x < -1.8) up to 0.1 m, its
    cab (-1.8 < x < 1.6) up to the roof (1.4); of its front (x > 2) no return came. With unseen_quantile 0.1 the
    front ends at the bed's top (+ the pad) and not at the box's; without it the front keeps its box."""
    from nuplan_occ.aggregation.carve import lattice_shape, under_top_envelope

    size = np.array([7.4, 2.3, 2.9])
    rng = np.random.default_rng(2)
    bed = np.column_stack([rng.uniform(-3.7, -1.8, 4000), rng.uniform(-1.15, 1.15, 4000), np.full(4000, 0.1)])
    cab = np.column_stack([rng.uniform(-1.8, 1.6, 6000), rng.uniform(-1.15, 1.15, 6000), np.full(6000, 1.4)])
    points = np.vstack([bed, cab])
    counts, edge = lattice_shape(size, 0.1)
    ijk = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), axis=-1).reshape(-1, 3)
    cells = (ijk + 0.5) * edge - size / 2
    settings = dict(reach_m=0.3, pad_m=0.1, floor_clearance_m=0.3, across_width=True)
    low = under_top_envelope(cells, points, size, 0.1, unseen_quantile=0.1, **settings)
    kept = under_top_envelope(cells, points, size, 0.1, **settings)
    front = cells[:, 0] > 2.0
    above_bed = cells[:, 2] - edge[2] / 2 > 0.1 + 0.1 + 1e-9
    assert not low[front & above_bed].any() and low[front & ~above_bed].all()
    assert kept[front].all()
    cab_inside = (np.abs(cells[:, 0]) < 1.2) & (cells[:, 2] < 1.4)
    assert low[cab_inside].all() and not low[(cells[:, 0] < -2.2) & above_bed].any()


def test_a_solid_ends_where_its_points_do_and_its_hidden_side_mirrors_the_seen_one():
    """A 4.6 x 1.9 x 1.5 m car in a box with 0.3 m of room on every side, seen only from its left (its left side,
    front and roof): no ray reaches its right side or the box's room there, so the carved solid fills the box up
    to its right face. Ended within the points' reach (side_quantile), the right side is the left one mirrored."""
    from nuplan_occ.aggregation.carve import TopEnvelope, object_solid_samples

    rng = np.random.default_rng(3)
    n = 3000
    left = np.column_stack([rng.uniform(-2.3, 2.3, n), np.full(n, 0.95), rng.uniform(-0.45, 0.75, n)])
    front = np.column_stack([np.full(n, 2.3), rng.uniform(-0.95, 0.95, n), rng.uniform(-0.45, 0.75, n)])
    roof = np.column_stack([rng.uniform(-2.3, 2.3, n), rng.uniform(-0.95, 0.95, n), np.full(n, 0.75)])
    points = np.vstack([left, front, roof])
    origins = np.broadcast_to([3.0, 10.0, 1.5], points.shape)
    size = np.array([5.2, 2.5, 1.5])
    _, edge = lattice_shape(size, 0.1)
    settings = dict(reach_m=0.3, pad_m=0.0, floor_clearance_m=0.3, across_width=True)
    boxed = object_solid_samples(points, origins, size, 0.1, None, False, TopEnvelope(**settings)).points
    ended = object_solid_samples(points, origins, size, 0.1, None, False,
                                 TopEnvelope(**settings, side_quantile=0.999)).points
    assert boxed[:, 1].min() < -1.15 and boxed[:, 0].min() < -2.5  # the hidden right side and rear fill the box
    assert ended[:, 1].min() >= -0.95 - edge[1] / 2 - 1e-9 and ended[:, 1].min() < -0.85  # mirrored, not cut
    assert ended[:, 0].min() >= -2.3 - edge[0] / 2 - 1e-9 and ended[:, 0].min() < -2.2
    inside = (np.abs(boxed[:, 0]) < 2.2) & (np.abs(boxed[:, 1]) < 0.85)
    assert inside.sum() == ((np.abs(ended[:, 0]) < 2.2) & (np.abs(ended[:, 1]) < 0.85)).sum()  # nothing else moves
