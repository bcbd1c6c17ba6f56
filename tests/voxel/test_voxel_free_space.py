"""Free-space consistency: a ground bulge the frame's rays cross is cleared; the ground voxel, measured
voxels and columns without a ground estimate are kept."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.grid import GridSpec
from nuplan_occ.voxel.free_space import point_support, unsupported_free_voxels
from nuplan_occ.voxel.visibility import FREE, OCCUPIED, lidar_observation

GRID = GridSpec(x_min=-5, x_max=5, y_min=-5, y_max=5, z_min=-1, z_max=1, voxel_size=0.25)
GROUND_Z = -0.86  # inside layer 0 ([-1, -0.75))


def scene():
    """Ground voxels everywhere (layer 0) plus a one-voxel bulge above it at x in [2, 3] (layer 1)."""
    occupied = np.zeros(GRID.shape, dtype=bool)
    occupied[:, :, 0] = True
    bulge = np.zeros(GRID.shape, dtype=bool)
    bulge[28:32, 18:22, 1] = True
    occupied |= bulge
    ground = np.full(GRID.shape[:2], GROUND_Z)
    # rays from a sensor 0.9 m up to ground returns beyond the bulge graze over the ground layer
    xs = np.linspace(3.2, 4.8, 30)
    ys = np.linspace(-0.4, 0.4, 9)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    returns = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, GROUND_Z)])
    observation = lidar_observation(returns, np.array([0.0, 0.0, 0.0]), GRID)
    return occupied, bulge, ground, returns, observation


def test_a_bulge_the_rays_cross_is_cleared_and_the_ground_stays():
    occupied, bulge, ground, returns, observation = scene()
    crossed = bulge & (observation == FREE)
    assert crossed.any()  # the set-up: rays do cross the bulge
    support = point_support(returns, GRID)
    clear = unsupported_free_voxels(occupied, observation, support, ground, GRID)
    assert np.array_equal(clear, crossed)
    assert not clear[:, :, 0].any()  # ground voxels, grazed by the same rays, are never cleared
    assert (observation[:, :, 0] == FREE).any()


def test_measured_voxels_and_unknown_ground_are_kept():
    occupied, bulge, ground, returns, observation = scene()
    support = point_support(np.vstack([returns, GRID.index_to_center(np.argwhere(bulge))]), GRID)
    assert not unsupported_free_voxels(occupied, observation, support, ground, GRID).any()
    no_ground = np.full(GRID.shape[:2], np.nan)
    assert not unsupported_free_voxels(occupied, observation, point_support(returns, GRID), no_ground, GRID).any()
    assert not unsupported_free_voxels(occupied, observation, point_support(returns, GRID), None, GRID).any()
    occupied_obs = np.where(bulge, OCCUPIED, observation).astype(np.uint8)  # a return inside: not free
    assert not unsupported_free_voxels(occupied, occupied_obs, point_support(returns, GRID), ground, GRID).any()


def test_shapes_are_checked():
    occupied, _, ground, returns, observation = scene()
    with pytest.raises(ValueError, match="observation"):
        unsupported_free_voxels(occupied, observation[:-1], point_support(returns, GRID), ground, GRID)
