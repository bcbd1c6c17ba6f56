"""The paper's vertex-only voxelization leaves holes that exact voxelization does not."""

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import OTHER, VEHICLE
from benchmarks.paper_method import midpoint_subdivide, paper_voxelize_vertices
from nuplan_occ.voxel.voxelize import voxelize_mesh

GRID = GridSpec(x_min=-8, x_max=8, y_min=-8, y_max=8, z_min=-2, z_max=2, voxel_size=0.25)


def test_paper_vertices_leave_holes_in_a_coarse_mesh():
    xs = np.arange(-6.0, 6.01, 1.0) + 0.05  # a flat 1 m triangulated grid at z = 0.1
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    vertices = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 0.1)], axis=1)
    n = len(xs)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    ours = voxelize_mesh(vertices, faces, GRID)
    paper = paper_voxelize_vertices(vertices, GRID, faces=faces)
    assert ours[:, :, 8].sum() == 49 * 49 and ours.sum() == 49 * 49  # the full 12 m x 12 m layer
    assert (paper > 0).sum() == 25 * 25  # vertices + edge midpoints: 0.5 m spacing, 3 of 4 voxels empty
    assert np.all(ours[paper > 0])


def test_majority_label_and_subdivision():
    v = np.array([[0.1, 0.1, 0.1], [0.12, 0.1, 0.1], [0.15, 0.1, 0.1], [1.1, 0.1, 0.1]])
    sem = paper_voxelize_vertices(v, GRID, labels=np.array([VEHICLE, VEHICLE, OTHER, OTHER]))
    assert sem[32, 32, 8] == VEHICLE and sem[36, 32, 8] == OTHER
    sub, _ = midpoint_subdivide(v[:3], np.array([[0, 1, 2]]))
    assert len(sub) == 6
