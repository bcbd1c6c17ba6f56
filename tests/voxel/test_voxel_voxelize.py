"""Exact surface voxelization against analytic voxel sets."""

import numpy as np
import pytest

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.voxel.voxelize import (
    VoxelizeError, box_voxel_indices, fill_box_interior, mesh_voxel_indices, voxelize_mesh, voxelize_points,
)

SMALL = GridSpec(x_min=-4, x_max=4, y_min=-4, y_max=4, z_min=-2, z_max=2, voxel_size=0.25)


def box_mesh(lo, hi):
    """12-triangle closed box surface between corners lo and hi."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return corners, faces


def test_large_triangle_equals_analytic_plane_layer():
    a, c, z = -40.1, 4.8, 0.1  # triangle x >= a, y >= a, x + y <= c at height z (inside layer 12)
    vertices = np.array([[a, a, z], [c - a, a, z], [a, c - a, z]])
    grid = voxelize_mesh(vertices, np.array([[0, 1, 2]]))
    x0 = DEFAULT_GRID.x_min + np.arange(400) * 0.25
    X0, Y0 = np.meshgrid(x0, x0, indexing="ij")
    # the half-open cell [x0, x0+s) x [y0, y0+s) meets the closed triangle
    analytic = (X0 + 0.25 > a) & (Y0 + 0.25 > a) & (np.maximum(X0, a) + np.maximum(Y0, a) <= c)
    assert np.array_equal(grid[:, :, 12], analytic)
    assert grid.sum() == analytic.sum()  # nothing outside layer 12, no holes


def test_plane_on_voxel_boundary_goes_to_upper_voxel():
    vertices = np.array([[-1.1, -1.1, 0.0], [1.1, -1.1, 0.0], [0.0, 1.1, 0.0]])
    grid = voxelize_mesh(vertices, np.array([[0, 1, 2]]), SMALL)
    assert set(np.nonzero(grid)[2].tolist()) == {8}  # z = 0 is the lower face of layer 8 (z_min = -2)


@pytest.mark.parametrize("yaw_free_offset", [0.0, 0.37])
def test_box_surface_and_fill_are_exact(yaw_free_offset):
    lo = np.array([-1.1, -0.6, -0.9]) + yaw_free_offset
    hi = np.array([1.3, 0.7, 0.4]) + yaw_free_offset
    vertices, faces = box_mesh(lo, hi)
    i_lo = np.floor((lo - SMALL.lower) / 0.25).astype(int)
    i_hi = np.floor((hi - SMALL.lower) / 0.25).astype(int)
    solid = np.zeros(SMALL.shape, dtype=bool)
    solid[i_lo[0]:i_hi[0] + 1, i_lo[1]:i_hi[1] + 1, i_lo[2]:i_hi[2] + 1] = True
    interior = np.zeros_like(solid)
    interior[i_lo[0] + 1:i_hi[0], i_lo[1] + 1:i_hi[1], i_lo[2] + 1:i_hi[2]] = True
    surface = voxelize_mesh(vertices, faces, SMALL)
    assert np.array_equal(surface, solid & ~interior)
    assert np.array_equal(voxelize_mesh(vertices, faces, SMALL, fill_solid=True), solid)


def test_fill_works_for_an_object_cut_by_the_grid_border():
    vertices, faces = box_mesh(np.array([3.1, -1.1, -1.1]), np.array([5.6, 1.1, 1.1]))
    filled = voxelize_mesh(vertices, faces, SMALL, fill_solid=True)
    assert filled[-1, 16, 8] and filled[-1].sum() == filled[-2].sum()  # interior up to the border


def test_every_surface_sample_lies_in_an_occupied_voxel():
    rng = np.random.default_rng(1)
    tri = rng.uniform(-3.5, 3.5, size=(200, 3, 3)) * [1, 1, 0.5]
    vertices, faces = tri.reshape(-1, 3), np.arange(600).reshape(-1, 3)
    occupied = mesh_voxel_indices(vertices, faces, SMALL)
    bary = rng.dirichlet([1, 1, 1], size=(200, 400))
    samples = np.einsum("tsk,tkd->tsd", bary, tri).reshape(-1, 3)
    idx, inside = SMALL.point_to_index(samples)
    sampled = {tuple(r) for r in idx[inside]}
    assert sampled <= {tuple(r) for r in occupied}
    assert len(occupied) < 1.3 * len(sampled)  # tight, not a bounding-box blow-up


def test_points_and_boxes():
    grid = voxelize_points(np.array([[0.1, 0.1, 0.1], [9.0, 0.0, 0.0]]), SMALL)
    assert grid.sum() == 1 and grid[16, 16, 8]
    idx = box_voxel_indices(np.zeros(3), np.pi / 2, np.array([2.0, 1.0, 1.0]), SMALL)
    span = idx.max(axis=0) - idx.min(axis=0) + 1
    assert span.tolist() == [4, 8, 4]  # rotated 90 deg: length along y
    assert fill_box_interior(np.zeros(SMALL.shape, bool), np.zeros(3), 0.0, np.array([1.0, 1, 1]), SMALL).sum() == 64


def test_bad_input_raises():
    with pytest.raises(VoxelizeError, match="face index"):
        mesh_voxel_indices(np.zeros((3, 3)), np.array([[0, 1, 5]]))
    with pytest.raises(VoxelizeError, match="NaN"):
        voxelize_points(np.array([[np.nan, 0, 0]]))
