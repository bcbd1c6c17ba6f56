"""nuplan_occ.rays.free_space.sorted_point_support: the support of an x-sorted scene aggregate in a frame's grid, from the
slice of points within the grid's window, equals the voxels of every point moved into the grid (numpy)."""

import numpy as np

from nuplan_occ.geometry import invert_transform, transform_points, yaw_matrix
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.rays.free_space import sorted_point_support


def test_the_window_slice_gives_the_support_of_every_point():
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-300, 300, 400_000), rng.uniform(-120, 120, 400_000), rng.uniform(-4, 6, 400_000)])
    points = points[np.argsort(points[:, 0], kind="stable")]
    for ego_x, ego_y, yaw in [(0.0, 0.0, 0.0), (150.0, -30.0, 0.8), (-260.0, 40.0, -2.5), (290.0, 0.0, np.pi / 2)]:
        T_scene_from_ego = np.eye(4)
        T_scene_from_ego[:3, :3] = yaw_matrix(yaw)
        T_scene_from_ego[:3, 3] = [ego_x, ego_y, 0.3]
        idx, inside = DEFAULT_GRID.point_to_index(transform_points(invert_transform(T_scene_from_ego), points))
        expected = np.zeros(DEFAULT_GRID.shape, dtype=bool)
        expected[tuple(idx[inside].T)] = True
        got = sorted_point_support(points, T_scene_from_ego)
        assert expected.sum() > 10_000  # the grid holds points in every case
        np.testing.assert_array_equal(got, expected)
