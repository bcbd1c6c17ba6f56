"""Unboxed movers: a frame's dynamic points become voxels labeled by their cluster's motion and size."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import BICYCLE, OTHER, VEHICLE
from nuplan_occ.voxel.movers import mover_voxels


def _surface_points(center, size, spacing=0.1) -> np.ndarray:
    """Points on the x-facing and top faces of a box (what one sweep sees of it), ego frame."""
    cx, cy, cz = center
    lx, ly, lz = size
    ys, zs = np.meshgrid(np.arange(cy - ly / 2, cy + ly / 2, spacing), np.arange(cz - lz / 2, cz + lz / 2, spacing))
    back = np.column_stack([np.full(ys.size, cx - lx / 2), ys.ravel(), zs.ravel()])
    xs, ys = np.meshgrid(np.arange(cx - lx / 2, cx + lx / 2, spacing), np.arange(cy - ly / 2, cy + ly / 2, spacing))
    top = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, cz + lz / 2 - 0.01)])
    return np.vstack([back, top])


def test_clusters_are_labeled_by_footprint_and_noise_is_skipped() -> None:
    truck = _surface_points((20.1, 5.1, 0.6), (8.0, 2.5, 3.0))
    pedestrian = _surface_points((10.1, -8.1, 0.0), (0.5, 0.5, 1.7))
    speck = np.array([[-30.1, 30.1, 1.1]])
    outside = np.array([[70.0, 0.0, 0.0]])
    result = mover_voxels(np.vstack([truck, pedestrian, speck, outside]), DEFAULT_GRID)
    centres = DEFAULT_GRID.lower + (result.indices + 0.5) * DEFAULT_GRID.voxel_size
    near_truck = np.abs(centres[:, 0] - 20.1) < 4.5
    near_pedestrian = np.abs(centres[:, 0] - 10.1) < 1.0
    assert near_truck.sum() and np.all(result.class_ids[near_truck] == VEHICLE)
    assert near_pedestrian.sum() and np.all(result.class_ids[near_pedestrian] == OTHER)
    assert np.all(near_truck | near_pedestrian)  # the lone speck and the point beyond the grid are not painted
    expected = np.unique(DEFAULT_GRID.point_to_index(np.vstack([truck, pedestrian]))[0], axis=0)
    assert len(np.unique(result.indices, axis=0)) == len(result.indices) == len(expected)


def test_fragments_near_a_vehicle_count_as_part_of_it() -> None:
    """A truck's roof whose middle stayed in the background: a 1 m piece one empty voxel from the rest joins
    its cluster (gap_voxels), and one three voxels away is a fragment of it (fragment_reach_m); on its own
    (neither) it is too short to be a vehicle."""
    roof = _surface_points((20.1, 5.1, 0.6), (8.0, 1.0, 3.0))
    roof = roof[roof[:, 2] > 2.0]
    piece = roof[:, 0] < 17.0
    def classes_of(result, points):
        voxels = np.unique(DEFAULT_GRID.point_to_index(points)[0], axis=0)
        hit = (result.indices[:, None, :] == voxels[None]).all(axis=2).any(axis=1)
        return set(result.class_ids[hit].tolist())
    for gap_m in (0.25, 0.75):
        gapped = roof[(roof[:, 0] < 17.0) | (roof[:, 0] >= 17.0 + gap_m)]
        assert classes_of(mover_voxels(gapped, DEFAULT_GRID), roof[piece]) == {VEHICLE}
        alone = mover_voxels(gapped, DEFAULT_GRID, gap_voxels=0, fragment_reach_m=0.0)
        assert VEHICLE not in classes_of(alone, roof[piece])


def test_no_points_no_voxels() -> None:
    result = mover_voxels(np.zeros((0, 3)), DEFAULT_GRID)
    assert result.indices.shape == (0, 3) and result.class_ids.shape == (0,)


def test_clusters_are_classed_by_ground_contact_length_and_motion() -> None:
    """On flat ground at z = -0.9 m: a cyclist (1.8 m) and a car (4.5 m) standing on it, a pedestrian (0.6 m),
    a group of posts (1.5 m) whose flagged points recur in another frame (static structure the dynamic test
    flagged) and a 3 m patch of canopy 3 m up. The cyclist is a bicycle though a tenth of its points recur by
    chance; the car is a vehicle though most of its points recur (it slides along its length); posts, canopy
    and pedestrian are `other`."""
    cyclist = _surface_points((12.1, 3.1, 0.0), (1.8, 0.6, 1.7))
    car = _surface_points((25.1, -6.1, -0.1), (4.5, 1.8, 1.5))
    pedestrian = _surface_points((8.1, -3.1, 0.0), (0.6, 0.6, 1.7))
    posts = _surface_points((-20.1, -12.1, -0.35), (1.5, 0.3, 1.0))
    canopy = _surface_points((-15.1, 12.1, 3.0), (3.0, 2.0, 0.5))
    parts = [cyclist, car, pedestrian, posts, canopy]
    rng = np.random.default_rng(0)
    recurring = [rng.random(len(cyclist)) < 0.1, rng.random(len(car)) < 0.6, np.zeros(len(pedestrian), bool),
                 rng.random(len(posts)) < 0.3, np.zeros(len(canopy), bool)]
    ground = np.full(DEFAULT_GRID.shape[:2], -0.9)
    ground[:10] = np.nan  # unknown ground far behind: no cluster there
    result = mover_voxels(np.vstack(parts), DEFAULT_GRID, recurring=np.concatenate(recurring), ground_height=ground)
    for part, expected in zip(parts, (BICYCLE, VEHICLE, OTHER, OTHER, OTHER)):
        voxels = np.unique(DEFAULT_GRID.point_to_index(part)[0], axis=0)
        hit = (result.indices[:, None, :] == voxels[None]).all(axis=2).any(axis=1)
        assert hit.sum() == len(voxels) and set(result.class_ids[hit].tolist()) == {expected}
    without = mover_voxels(np.vstack(parts), DEFAULT_GRID)  # no ground, no other frames: all stand, none known to move
    for part, expected in ((canopy, VEHICLE), (cyclist, OTHER), (posts, OTHER)):
        voxels = np.unique(DEFAULT_GRID.point_to_index(part)[0], axis=0)
        hit = (without.indices[:, None, :] == voxels[None]).all(axis=2).any(axis=1)
        assert set(without.class_ids[hit].tolist()) == {expected}


def test_a_bicycle_reaches_down_to_its_ground_and_replaces_the_background_there() -> None:
    """Ground at z = -0.9 m (voxel layer 8). A cyclist's frame (1.8 m long, 0.1 m wide) seen from 0.3 m above
    the ground (its wheels' lowest returns were not flagged) and its rider (0.5 m long, 0.7 m wide) from
    0.9 m up: the frame's columns gain their ground voxel, the rider's columns (1.5 m up) gain nothing. A
    pedestrian seen from 0.3 m up gains nothing (not a bicycle). Painted into a frame whose ground layer is
    background, the wheel voxels replace it and stop being background."""
    from nuplan_occ.voxel.compose import FrameGrids
    from nuplan_occ.voxel.movers import paint_empty

    xs, zs = np.meshgrid(np.arange(11.2, 13.0, 0.1), np.arange(-0.6, 0.3, 0.1))
    frame = np.column_stack([xs.ravel(), np.full(xs.size, 3.05), zs.ravel()])  # its side, as a sweep sees it
    rider = _surface_points((12.1, 3.1, 0.4), (0.5, 0.7, 0.8))
    pedestrian = _surface_points((8.1, -3.1, 0.25), (0.6, 0.6, 1.1))
    ground = np.full(DEFAULT_GRID.shape[:2], -0.9)
    points = np.vstack([frame, rider, pedestrian])
    recurring = np.zeros(len(points), bool)
    result = mover_voxels(points, DEFAULT_GRID, recurring=recurring, ground_height=ground)
    wheels = result.indices[result.over_ground]
    frame_columns = np.unique(DEFAULT_GRID.point_to_index(frame)[0][:, :2], axis=0)
    assert np.all(result.class_ids[result.over_ground] == BICYCLE) and np.all(wheels[:, 2] == 8)
    np.testing.assert_array_equal(np.unique(wheels[:, :2], axis=0), frame_columns)
    none_filled = mover_voxels(points, DEFAULT_GRID, recurring=recurring, ground_height=ground, bicycle_ground_fill_m=0.0)
    assert not none_filled.over_ground.any() and len(none_filled.indices) == len(result.indices) - len(wheels)

    shape = DEFAULT_GRID.shape
    semantics = np.zeros(shape, np.uint8)
    semantics[:, :, 8] = OTHER
    grids = FrameGrids(semantics, np.zeros(shape, np.uint16), np.zeros((*shape, 3), np.float16), semantics > 0, ground)
    painted = paint_empty(grids, result)
    assert painted == len(result.indices)
    i, j, k = wheels.T
    assert np.all(grids.semantics[i, j, k] == BICYCLE) and not grids.occupied_background[i, j, k].any()
    assert grids.occupied_background.sum() == shape[0] * shape[1] - len(wheels)


def test_neighbour_movers_are_the_frames_the_given_count_before_and_after() -> None:
    from nuplan_occ.voxel.movers import neighbour_movers

    frame_movers = {position: np.full((1, 3), float(position)) for position in (30, 10, 20, 40, 50)}
    before, after = neighbour_movers(frame_movers, 30, 2)  # output frames in position order, not insertion order
    assert before[0, 0] == 10.0 and after[0, 0] == 50.0
    assert neighbour_movers(frame_movers, 20, 2) == []  # no frame two before it
    assert neighbour_movers(frame_movers, 40, 1)[1][0, 0] == 50.0


def test_a_class_left_out_of_the_rule_gives_the_neutral_label() -> None:
    """With classes=(VEHICLE,) the cyclist of the scene above is `other` (and gains no wheel columns) while the
    car stays a vehicle."""
    cyclist = _surface_points((12.1, 3.1, 0.0), (1.8, 0.6, 1.7))
    car = _surface_points((25.1, -6.1, -0.1), (4.5, 1.8, 1.5))
    ground = np.full(DEFAULT_GRID.shape[:2], -0.9)
    recurring = np.zeros(len(cyclist) + len(car), bool)
    result = mover_voxels(np.vstack([cyclist, car]), DEFAULT_GRID, recurring=recurring, ground_height=ground,
                          classes=(VEHICLE,))
    for part, expected in ((cyclist, OTHER), (car, VEHICLE)):
        voxels = np.unique(DEFAULT_GRID.point_to_index(part)[0], axis=0)
        hit = (result.indices[:, None, :] == voxels[None]).all(axis=2).any(axis=1)
        assert set(result.class_ids[hit].tolist()) == {expected}
    assert not result.over_ground.any() and BICYCLE not in result.class_ids


def test_a_short_moving_cluster_below_a_riders_height_is_no_bicycle() -> None:
    """The back of a car seen from behind (1.8 m wide, its flagged part 1.1 m tall above the ground clearance) moves
    like a cyclist, but its top stands 1.4 m above the ground: `other` with bicycle_min_height_m 1.5; the cyclist
    (1.7 m) stays a bicycle."""
    ground = np.full(DEFAULT_GRID.shape[:2], -0.9)
    cyclist = _surface_points((12.1, 3.1, 0.0), (1.8, 0.6, 1.7))
    car_back = _surface_points((20.1, -3.1, -0.9 + 0.3 + 0.55), (0.3, 1.8, 1.1))
    result = mover_voxels(np.vstack([cyclist, car_back]), DEFAULT_GRID,
                          recurring=np.zeros(len(cyclist) + len(car_back), bool), ground_height=ground,
                          bicycle_min_height_m=1.5)
    for part, expected in ((cyclist, BICYCLE), (car_back, OTHER)):
        voxels = np.unique(DEFAULT_GRID.point_to_index(part)[0], axis=0)
        hit = (result.indices[:, None, :] == voxels[None]).all(axis=2).any(axis=1)
        assert set(result.class_ids[hit].tolist()) == {expected}


def test_a_moving_cluster_wide_across_its_motion_is_no_bicycle() -> None:
    """A cyclist riding along x seen side-on (1.8 m long, 0.6 m wide) and the back of a car driving away along x
    seen from behind (0.3 m deep, 1.8 m wide, 1.7 m tall: a rider's height): the frames 0.5 s before and after
    hold each one 2.5 m behind and ahead, and a post flagged in both (static: tells no motion). Across its motion
    the cyclist spans < 1 m and stays a bicycle; the car's back spans 1.8 m: `other`. Without an earlier frame's
    points the motion is unknown: neither is a bicycle; without neighbours the rule is not applied."""
    ground = np.full(DEFAULT_GRID.shape[:2], -0.9)
    cyclist = _surface_points((12.1, 3.1, 0.0), (1.8, 0.6, 1.7))
    car_back = _surface_points((20.1, -6.1, -0.05), (0.3, 1.8, 1.7))
    post = _surface_points((16.1, -1.1, -0.4), (0.2, 0.2, 1.0))
    shift = np.array([2.5, 0.0, 0.0])
    before = np.vstack([cyclist - shift, car_back - shift, post])
    after = np.vstack([cyclist + shift, car_back + shift, post])
    points = np.vstack([cyclist, car_back])
    common = dict(recurring=np.zeros(len(points), bool), ground_height=ground, bicycle_max_width_m=1.5)

    def classes(result, part) -> set[int]:
        voxels = np.unique(DEFAULT_GRID.point_to_index(part)[0], axis=0)
        hit = (result.indices[:, None, :] == voxels[None]).all(axis=2).any(axis=1)
        return set(result.class_ids[hit].tolist())

    read = mover_voxels(points, DEFAULT_GRID, neighbours=(before, after), **common)
    assert classes(read, cyclist) == {BICYCLE} and classes(read, car_back) == {OTHER}
    unknown = mover_voxels(points, DEFAULT_GRID, neighbours=(post, after), **common)
    assert classes(unknown, cyclist) == {OTHER} and classes(unknown, car_back) == {OTHER}
    not_read = mover_voxels(points, DEFAULT_GRID, **common)
    assert classes(not_read, cyclist) == {BICYCLE} and classes(not_read, car_back) == {BICYCLE}


def test_a_cluster_taller_than_any_vehicle_is_not_one() -> None:
    """A 12 m stretch of facade 5 m tall that the dynamic test flagged, beside a 3.5 m truck, both standing on
    the ground at z = -0.4 m: the truck is a vehicle, the facade is other."""
    ground = np.full(DEFAULT_GRID.shape[:2], -0.4)
    ys, zs = np.meshgrid(np.arange(-6.0, 6.0, 0.1), np.arange(-0.3, 4.6, 0.1))
    facade = np.c_[np.full(ys.size, 30.1), ys.ravel(), zs.ravel()]
    truck = _surface_points((15.1, 0.1, -0.4 + 1.75), (8.0, 2.5, 3.5))
    result = mover_voxels(np.vstack([facade, truck]), DEFAULT_GRID, ground_height=ground, vehicle_max_height_m=4.5)
    centres = DEFAULT_GRID.index_to_center(result.indices)
    at_facade = centres[:, 0] > 29.0
    assert at_facade.any() and np.all(result.class_ids[at_facade] == OTHER)
    assert np.all(result.class_ids[~at_facade] == VEHICLE)
    unbounded = mover_voxels(np.vstack([facade, truck]), DEFAULT_GRID, ground_height=ground)
    assert np.all(unbounded.class_ids == VEHICLE)  # without the bound the facade passes for a vehicle
