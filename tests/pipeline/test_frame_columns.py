"""Per-frame columns: point coverage counts a sweep's returns in or next to an occupied voxel."""

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.pipeline.frame_columns import point_coverage

GRID = GridSpec(x_min=-2, x_max=2, y_min=-2, y_max=2, z_min=-1, z_max=1, voxel_size=0.25)


def test_point_coverage_counts_the_26_neighbourhood_only():
    occupied = np.zeros(GRID.shape, dtype=bool)
    occupied[5, 5, 3] = occupied[0, 0, 0] = True
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    index = np.array([5, 5, 3]) + offsets  # 27 of these 125 voxels touch (5, 5, 3)
    centre = GRID.index_to_center(index)
    assert point_coverage(centre, occupied, GRID) == 27 / 125
    corner = GRID.index_to_center(np.array([[1, 1, 1], [2, 0, 0], [1, 2, 1]]))  # at the grid's corner voxel
    outside = GRID.lower - 0.1  # ignored
    assert point_coverage(np.vstack([corner, outside]), occupied, GRID) == 1 / 3
    assert np.isnan(point_coverage(outside[None], occupied, GRID))
