"""LiDAR ray traversal and camera occlusion on hand-checked geometry."""

import numpy as np
import pytest

from nuplan_occ.geometry import make_transform
from nuplan_occ.grid import GridSpec
from nuplan_occ.io.types import CameraCalibration
from nuplan_occ.rays.traversal import grid_args
from nuplan_occ.rays.visibility import (
    FREE, OCCUPIED, VisibilityError, camera_visibility, lidar_observation, lidar_visibility,
)

GRID = GridSpec(x_min=-10, x_max=10, y_min=-10, y_max=10, z_min=-2, z_max=2, voxel_size=0.25)


def test_single_diagonal_ray_marks_exactly_the_traversed_voxels():
    origin = np.array([0.1, 0.1, 0.1])  # voxel units (40.4, 40.4, 8.4)
    ret = np.array([[1.0, 0.6, 0.35]])  # voxel units (44, 42.4, 9.4); d = (3.6, 2.0, 1.0)
    obs = lidar_observation(ret, origin, GRID)
    # crossings: x at t=1/6, 4/9, 13/18; y at 0.3, 0.8; z at 0.6; the x plane 44 at t = 1 is the return
    free = [(40, 40, 8), (41, 40, 8), (41, 41, 8), (42, 41, 8), (42, 41, 9), (43, 41, 9), (43, 42, 9)]
    assert sorted(map(tuple, np.argwhere(obs == FREE))) == free
    assert [tuple(r) for r in np.argwhere(obs == OCCUPIED)] == [(44, 42, 9)]
    assert lidar_visibility(ret, origin, GRID).sum() == 8


def test_ray_leaving_the_grid_and_many_rays_agree_with_dense_sampling():
    rng = np.random.default_rng(3)
    origin = np.array([0.3, -0.2, 0.4])
    ends = origin + rng.normal(size=(300, 3)) * [8, 8, 1.5]
    obs = lidar_observation(ends, origin, GRID)
    t = np.linspace(0, 1, 4001)[:-1]
    samples = origin + t[None, :, None] * (ends - origin)[:, None, :]
    idx, inside = GRID.point_to_index(samples.reshape(-1, 3))
    sampled = np.zeros(GRID.shape, bool)
    sampled[tuple(idx[inside].T)] = True
    assert np.all(obs[sampled] > 0)  # every sampled voxel is observed
    assert (obs > 0).sum() <= sampled.sum() + 300 + 150  # and little more (corner slivers, returns)


def test_rays_to_non_finite_returns_are_ignored():
    rng = np.random.default_rng(4)
    origin = np.array([0.3, -0.2, 0.4])
    ends = origin + rng.normal(size=(200, 3)) * [8, 8, 1.5]
    bad = np.array([[np.nan, 0, 0], [np.inf, 1, 0], [-np.inf, -np.inf, np.nan]])
    with np.errstate(invalid="ignore"):  # the return voxel of a NaN point is looked up (and dropped) too
        with_bad = lidar_observation(np.vstack([ends[:100], bad, ends[100:]]), origin, GRID)
    assert np.array_equal(with_bad, lidar_observation(ends, origin, GRID))


def test_wall_occludes_what_is_behind_it():
    # camera at the origin looking along +x (OpenCV axes: z_cam = x_ego, x_cam = -y_ego, y_cam = -z_ego)
    R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    K = np.array([[100.0, 0, 100], [0, 100.0, 50], [0, 0, 1]])
    cam = CameraCalibration("c", "CAM_F0", "pinhole", K, np.zeros(5), make_transform(R, [0.0, 0, 0.1]), 200, 100)
    occ = np.zeros(GRID.shape, bool)
    occ[60, 30:50, :] = True  # a wall at x in [5, 5.25), y in [-2.5, 2.5)
    vis = camera_visibility(occ, [cam], GRID, max_range_m=9.0)
    assert vis[60, 40, 8] and vis[50, 40, 8] and vis[41, 40, 8]  # wall and free space before it
    assert not vis[61:, 35:45, 6:10].any()  # behind the wall
    assert vis[64, 52, 8]  # beside the wall's edge, inside the frustum
    assert not vis[30, 40, 8] and not vis[60, 79, 8]  # behind the camera; outside the 90 deg field of view
    assert not vis[76:, 40, 8].any()  # beyond max range


def test_bad_rays_raise():
    with pytest.raises(VisibilityError):
        lidar_visibility(np.zeros((4, 2)), np.zeros(3), GRID)


def test_a_grid_too_large_for_int32_voxel_indices_is_refused():
    huge = GridSpec(x_min=-500, x_max=500, y_min=-500, y_max=500, z_min=-3, z_max=5, voxel_size=0.05)  # 3.2e10 voxels
    with pytest.raises(ValueError, match="fewer than"):
        grid_args(huge)
