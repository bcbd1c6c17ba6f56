"""nuplan_occ.voxel.placement: the box lattice of box-filled objects."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.voxel.placement import box_lattice_points
from nuplan_occ.voxel.voxelize import mesh_voxel_indices


def test_box_lattice_covers_the_box_faces_included():
    size = np.array([0.62, 0.58, 1.8])
    points = box_lattice_points(size, 0.05)
    np.testing.assert_allclose(points.min(axis=0), -size / 2)
    np.testing.assert_allclose(points.max(axis=0), size / 2)
    step = [np.diff(np.unique(points[:, a])).max() for a in range(3)]
    assert max(step) <= 0.05 + 1e-12


def test_box_lattice_voxelizes_to_every_voxel_the_box_overlaps():
    grid = GridSpec(x_min=-2, x_max=2, y_min=-2, y_max=2, z_min=-1, z_max=3, voxel_size=0.25)
    center = np.array([0.1, -0.2, 0.95])  # box x [-0.2, 0.4], y [-0.5, 0.1], z [0.05, 1.85]
    points = box_lattice_points(np.array([0.6, 0.6, 1.8]), 0.05) + center
    idx = mesh_voxel_indices(points, np.zeros((0, 3), dtype=np.int64), grid)
    # x voxels [-0.25, 0.5) -> 3, y [-0.5, 0.25) -> 3 (0.1 lies inside [0, 0.25)), z [0, 2.0) -> 8
    assert len(idx) == 3 * 3 * 8
