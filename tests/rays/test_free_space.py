"""Free-space consistency: a ground bulge rays cross is cleared, by this frame's rays or another frame's
(moved into this frame's grid); the ground voxel, measured voxels and columns without a ground estimate
are kept. Object voxels of the chosen classes that the frame's own rays crossed are cleared unless they
hold one of the objects' points; boxed object voxels the rays crossed are cleared where no object point lies
near their column."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.geometry import make_transform
from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import LABELS
from nuplan_occ.rays.free_space import (clearable_background, crossed_far_from_points, crossed_objects, free_in_other_frames,
                                        point_support)
from nuplan_occ.rays.visibility import FREE, OCCUPIED, UNKNOWN, lidar_observation, lidar_observation_bits

GRID = GridSpec(x_min=-5, x_max=5, y_min=-5, y_max=5, z_min=-1, z_max=1, voxel_size=0.25)
GROUND_Z = -0.86  # inside layer 0 ([-1, -0.75))


def packed_free(observation: np.ndarray) -> np.ndarray:
    """The FREE voxels of an observation grid as np.packbits of the flat C-order grid (the FREE bits of
    `lidar_observation_bits`, made here from a grid built by hand)."""
    return np.packbits((np.asarray(observation) == FREE).reshape(-1))

def scene(sensor_x: float = 0.0):
    """Ground voxels everywhere (layer 0) plus a one-voxel bulge above it at x in [2, 3] (layer 1); rays
    from a sensor at (sensor_x, 0, 0) to ground returns at x in [3.2, 4.8] graze over the ground layer."""
    occupied = np.zeros(GRID.shape, dtype=bool)
    occupied[:, :, 0] = True
    bulge = np.zeros(GRID.shape, dtype=bool)
    bulge[28:32, 18:22, 1] = True
    occupied |= bulge
    ground = np.full(GRID.shape[:2], GROUND_Z)
    X, Y = np.meshgrid(np.linspace(3.2, 4.8, 30), np.linspace(-0.4, 0.4, 9), indexing="ij")
    returns = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, GROUND_Z)])
    observation = lidar_observation(returns - [sensor_x, 0.0, 0.0], np.zeros(3), GRID)  # in that sensor's grid
    return occupied, bulge, ground, returns, observation


def test_a_bulge_the_rays_cross_is_cleared_and_the_ground_stays():
    occupied, bulge, ground, returns, observation = scene()
    candidates = clearable_background(occupied, point_support(returns, GRID), ground, GRID)
    assert np.array_equal(candidates, bulge)  # unmeasured and above the ground voxel
    centres = GRID.index_to_center(np.argwhere(candidates))
    free = free_in_other_frames(centres, [np.eye(4)], [packed_free(observation)], GRID)
    crossed = (observation == FREE)[tuple(np.argwhere(candidates).T)]
    assert crossed.any() and np.array_equal(free, crossed)
    assert (observation[:, :, 0] == FREE).any()  # the same rays graze ground voxels, which are no candidates


def test_another_frames_rays_clear_what_this_frame_did_not_see():
    occupied, bulge, ground, returns, _ = scene()
    # the other frame's ego sits 1 m further along x: its grid is this one shifted by -1 m
    _, _, _, _, other = scene(sensor_x=1.0)
    T_other_from_this = make_transform(np.eye(3), [-1.0, 0.0, 0.0])
    centres = GRID.index_to_center(np.argwhere(bulge))
    nothing_here = np.zeros(GRID.shape, dtype=np.uint8)
    own_only = free_in_other_frames(centres, [np.eye(4)], [packed_free(nothing_here)], GRID)
    both = free_in_other_frames(centres, [np.eye(4), T_other_from_this], [packed_free(nothing_here), packed_free(other)], GRID)
    assert not own_only.any() and both.any()
    moved = centres + [-1.0, 0.0, 0.0]
    idx, inside = GRID.point_to_index(moved)
    assert np.array_equal(both, inside & (other[tuple(idx.T)] == FREE))


def test_measured_voxels_and_unknown_ground_are_kept():
    occupied, bulge, ground, returns, _ = scene()
    support = point_support(np.vstack([returns, GRID.index_to_center(np.argwhere(bulge))]), GRID)
    assert not clearable_background(occupied, support, ground, GRID).any()
    no_ground = np.full(GRID.shape[:2], np.nan)
    assert not clearable_background(occupied, point_support(returns, GRID), no_ground, GRID).any()
    assert not clearable_background(occupied, point_support(returns, GRID), None, GRID).any()


def test_shapes_are_checked():
    occupied, _, ground, returns, observation = scene()
    with pytest.raises(ValueError, match="support"):
        clearable_background(occupied, point_support(returns, GRID)[:-1], ground, GRID)
    with pytest.raises(ValueError, match="packed bits"):
        free_in_other_frames(np.zeros((1, 3)), [np.eye(4)], [packed_free(observation)[:-1]], GRID)


def test_an_observation_comes_back_whole_from_its_observed_and_free_bits():
    returns, observation = scene()[3:]
    assert {UNKNOWN, FREE, OCCUPIED} <= set(np.unique(observation).tolist())
    observed_bits, free_bits = lidar_observation_bits(returns, np.zeros(3), GRID)
    np.testing.assert_array_equal(free_bits, packed_free(observation))
    observed, free = (np.unpackbits(bits, count=observation.size).reshape(GRID.shape) == 1
                      for bits in (observed_bits, free_bits))
    np.testing.assert_array_equal(observed, observation != UNKNOWN)
    np.testing.assert_array_equal(free, observation == FREE)
    np.testing.assert_array_equal(observed & ~free, observation == OCCUPIED)


def test_object_voxels_the_rays_crossed_are_cleared_unless_they_hold_an_object_point():
    pedestrian, vehicle = LABELS.box_category_to_id["pedestrian"], LABELS.box_category_to_id["vehicle"]
    # one ray from the origin along +x at y = z = 0.1 (voxel row y 20, z 4), returning at x = 4.8
    observation = lidar_observation(np.array([[4.8, 0.1, 0.1]]), np.zeros(3), GRID)
    semantics = np.zeros(GRID.shape, dtype=np.uint8)
    held, crossed, other_class, aside = (24, 20, 4), (28, 20, 4), (32, 20, 4), (28, 25, 4)
    for voxel, label in ((held, pedestrian), (crossed, pedestrian), (other_class, vehicle), (aside, pedestrian)):
        semantics[voxel] = label
    object_points = np.zeros(GRID.shape, dtype=bool)
    object_points[held] = True  # a point of the pedestrian from a neighbouring sweep
    assert observation[held] == observation[crossed] == observation[other_class] == FREE
    assert observation[aside] == UNKNOWN
    cleared = crossed_objects(semantics, (pedestrian,), object_points, packed_free(observation), GRID)
    assert {tuple(v) for v in np.argwhere(cleared)} == {crossed}
    both = crossed_objects(semantics, (pedestrian, vehicle), object_points, packed_free(observation), GRID)
    assert {tuple(v) for v in np.argwhere(both)} == {crossed, other_class}


def test_crossed_box_voxels_far_from_every_object_point_are_cleared():
    """A box 3 m long along x at y = z = 0.1 (row y 20, layer 4), whose returns all came from its near half
    (x < 2 m). One ray runs along the row to x = 4.8: the box's far end lies more than 0.5 m from every column
    holding a point and is cleared; crossed voxels within 0.5 m of them stay, and so does a far voxel no ray
    crossed."""
    observation = lidar_observation(np.array([[4.8, 0.1, 0.1]]), np.zeros(3), GRID)
    box = np.zeros(GRID.shape, dtype=bool)
    box[24:32, 19:22, 4] = True  # x in [1, 3) m
    object_points = np.zeros(GRID.shape, dtype=bool)
    object_points[24:28, 20, 4] = True  # returns at x in [1, 2) m
    cleared = crossed_far_from_points(box, object_points, packed_free(observation), 0.5, GRID)
    # columns x index 28, 29 lie within 2 columns (0.5 m) of index 27, which holds points; 30, 31 beyond
    assert {tuple(v) for v in np.argwhere(cleared)} == {(30, 20, 4), (31, 20, 4)}
    assert observation[31, 21, 4] == UNKNOWN and not cleared[31, 21, 4]  # no ray crossed it
    assert not crossed_far_from_points(box, object_points, packed_free(observation), 2.0, GRID).any()
