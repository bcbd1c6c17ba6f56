"""Ray consistency on hand-made grids with known answers: a wall the rays end on, a slab in front of it, the
wall removed or moved, the road met at a grazing angle, returns that are not scored."""

import numpy as np
import pytest

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import OTHER, ROAD
from nuplan_occ.rays.consistency import (AGREE, EARLY, HOLE, NOT_SCORED, OTHER as OUTCOME_OTHER, ray_consistency,
                                         ray_outcomes)

GRID = GridSpec(x_min=-5.0, x_max=35.0, y_min=-10.0, y_max=10.0, z_min=-2.0, z_max=4.0, voxel_size=0.25)
ORIGIN = np.array([0.1, 0.05, 1.6])
WALL_X = 20.1
"""The rays' surface: a wall at x = 20.1 m (voxel index 100 along x, covering [20.0, 20.25))."""


def _index(x: float, axis: int = 0) -> int:
    return int(np.floor((x - GRID.lower[axis]) / GRID.voxel_size))


def _wall_grid(wall_x: float = WALL_X) -> np.ndarray:
    grid = np.zeros(GRID.shape, dtype=np.uint8)
    grid[_index(wall_x)] = OTHER
    return grid


def _wall_returns() -> np.ndarray:
    """60 returns on the wall plane, spread over y in [-6, 6) m and z in [-0.5, 3) m."""
    y, z = np.meshgrid(np.linspace(-6.0, 5.9, 10), np.linspace(-0.5, 2.9, 6), indexing="ij")
    return np.stack([np.full(y.size, WALL_X), y.ravel(), z.ravel()], axis=1)


def test_rays_ending_on_the_wall_agree_with_no_depth_error():
    outcome, error = ray_outcomes(_wall_grid(), ORIGIN, _wall_returns(), GRID)
    assert np.all(outcome == AGREE)
    assert np.all(error == 0.0)
    figures = ray_consistency(_wall_grid(), ORIGIN, _wall_returns(), GRID)
    assert (figures.n_scored, figures.agree, figures.early, figures.hole, figures.other) == (60, 1.0, 0.0, 0.0, 0.0)


def test_a_slab_in_front_of_the_wall_makes_its_rays_early_by_the_gap():
    """A slab at x in [10.0, 10.25) covering y in [-2, 2) at every height: rays through it end early by the
    distance from where they enter it to the return (r - d, the same ratio of r for every ray: the slab is at
    x = 10.0); the other rays still agree."""
    grid = _wall_grid()
    grid[_index(10.0), _index(-2.0, 1):_index(2.0, 1)] = OTHER
    returns = _wall_returns()
    outcome, error = ray_outcomes(grid, ORIGIN, returns, GRID)
    r = np.linalg.norm(returns - ORIGIN, axis=1)
    t_slab = (10.0 - ORIGIN[0]) / (returns[:, 0] - ORIGIN[0])
    y_at_slab = ORIGIN[1] + t_slab * (returns[:, 1] - ORIGIN[1])
    through = (y_at_slab >= -2.0) & (y_at_slab < 2.0)
    assert through.sum() == 36 and np.all(outcome[through] == EARLY) and np.all(outcome[~through] == AGREE)
    np.testing.assert_allclose(error[through], (r * (1.0 - t_slab))[through], atol=1e-9)
    figures = ray_consistency(grid, ORIGIN, returns, GRID)
    assert figures.early == pytest.approx(36 / 60) and figures.agree == pytest.approx(24 / 60)


def test_a_removed_wall_is_a_hole_for_every_ray():
    outcome, error = ray_outcomes(np.zeros(GRID.shape, np.uint8), ORIGIN, _wall_returns(), GRID)
    assert np.all(outcome == HOLE) and np.all(np.isnan(error))
    assert ray_consistency(np.zeros(GRID.shape, np.uint8), ORIGIN, _wall_returns(), GRID).hole == 1.0


def test_a_wall_drawn_half_a_metre_early_is_neither_agreement_nor_early():
    """The wall two voxels in front: each ray ends ~0.5 m early (more than a voxel, less than EARLY_M)."""
    outcome, error = ray_outcomes(_wall_grid(WALL_X - 0.5), ORIGIN, _wall_returns(), GRID)
    assert np.all(outcome == OUTCOME_OTHER)
    assert np.all((error > 0.25) & (error < 0.7))


def test_a_wall_one_voxel_off_still_agrees_and_beside_the_ray_is_no_hole():
    assert np.all(ray_outcomes(_wall_grid(WALL_X - 0.25), ORIGIN, _wall_returns(), GRID)[0] == AGREE)
    assert np.all(ray_outcomes(_wall_grid(WALL_X + 0.25), ORIGIN, _wall_returns(), GRID)[0] == AGREE)
    # the wall two voxels behind the return: the ray stops a voxel past it, the wall is not a neighbour
    assert np.all(ray_outcomes(_wall_grid(WALL_X + 0.5), ORIGIN, _wall_returns(), GRID)[0] == HOLE)


def test_grazing_road_agrees_but_the_same_layer_of_another_class_ends_early():
    """Returns on a flat road at z = -0.1 m, 25 - 30 m ahead: the ray enters the road's voxel layer
    [-0.25, 0) about 1.5 m before the return. Labelled road, that is the road seen at a grazing angle;
    labelled `other`, a slab lying there would end the rays early."""
    returns = np.stack([np.linspace(25.0, 30.0, 20), np.linspace(-3.0, 3.0, 20), np.full(20, -0.1)], axis=1)
    layer = np.zeros(GRID.shape, dtype=np.uint8)
    layer[:, :, _index(-0.1, 2)] = ROAD
    assert np.all(ray_outcomes(layer, ORIGIN, returns, GRID)[0] == AGREE)
    layer[layer == ROAD] = OTHER
    outcome, error = ray_outcomes(layer, ORIGIN, returns, GRID)
    assert np.all(outcome == EARLY) and np.all(error > 1.0)
    # the road a metre above the return is no grazing agreement either
    lifted = np.zeros(GRID.shape, dtype=np.uint8)
    lifted[:, :, _index(0.9, 2)] = ROAD
    assert np.all(ray_outcomes(lifted, ORIGIN, returns, GRID)[0] == EARLY)


def test_returns_outside_the_grid_or_at_the_origin_are_not_scored_and_max_rays_strides():
    returns = np.concatenate([_wall_returns(), [[40.0, 0.0, 1.0], [20.0, 0.0, 4.5], ORIGIN + 0.1]])
    outcome, error = ray_outcomes(_wall_grid(), ORIGIN, returns, GRID)
    assert np.all(outcome[:60] == AGREE) and np.all(outcome[60:] == NOT_SCORED) and np.all(np.isnan(error[60:]))
    figures = ray_consistency(_wall_grid(), ORIGIN, returns, GRID, max_rays=20)
    assert (figures.n_returns, figures.n_scored) == (63, 15)  # every 4th return (0, 4, ..., 60): 15 on the wall
    empty = ray_consistency(_wall_grid(), ORIGIN, returns[60:], GRID)
    assert empty.n_scored == 0 and np.isnan(empty.agree) and np.isnan(empty.depth_error_p99_m)
