"""Points moved into another grid's frame: exact voxels for a quarter turn plus whole-voxel shifts (integer
arithmetic gives the truth), the same voxels as numpy's transform for a generic pose, and the first-hit
lookup over several frames equal to the OR of per-frame lookups in any frame order."""

import numpy as np

from nuplan_occ.geometry import invert_transform, make_transform, transform_points, yaw_matrix
from nuplan_occ.grid import GridSpec
from nuplan_occ.voxel.frame_lookup import any_bit_set, flat_voxels, mark_points
from nuplan_occ.rays.traversal import grid_args

GRID = GridSpec(x_min=-4, x_max=4, y_min=-3, y_max=3, z_min=-1, z_max=1, voxel_size=0.25)
QUARTER = make_transform(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), [0.5, -0.75, 0.25])  # yaw 90 deg


def centres_of(idx):
    return GRID.index_to_center(idx)


def test_quarter_turn_maps_voxel_centres_to_the_expected_voxels():
    rng = np.random.default_rng(0)
    idx = np.stack([rng.integers(0, n, 500) for n in GRID.shape], axis=1)
    out = np.zeros(int(np.prod(GRID.shape)) + 1, bool)  # the grid and the spare element
    mark_points(centres_of(idx), QUARTER, *grid_args(GRID), out)
    assert out[-1]  # set by the points moved out of the grid
    out = out[:-1]
    # (x, y, z) -> (-y + 0.5, x - 0.75, z + 0.25) moves voxel centres to voxel centres: with x = -4 + (i + 0.5) / 4
    # and y = -3 + (j + 0.5) / 4, voxel (i, j, k) goes to (29 - j, i - 7, k + 1)
    moved = np.stack([29 - idx[:, 1], idx[:, 0] - 7, idx[:, 2] + 1], axis=1)
    inside = np.all((moved >= 0) & (moved < GRID.shape), axis=1)
    expected = np.zeros(GRID.shape, bool)
    expected[tuple(moved[inside].T)] = True
    assert 0 < inside.sum() < len(idx)
    assert np.array_equal(out.reshape(GRID.shape), expected)


def test_generic_pose_agrees_with_numpy_transform_in_whole_blocks_and_the_rest():
    rng = np.random.default_rng(1)
    T = make_transform(yaw_matrix(0.37) @ np.array([[1, 0, 0], [0, np.cos(0.02), -np.sin(0.02)], [0, np.sin(0.02), np.cos(0.02)]]),
                       [0.31, -0.17, 0.05])
    points = rng.uniform(-8, 8, size=(40005, 3)) * [1, 1, 0.3]  # not a whole number of blocks
    points[:3] = [np.nan, 0, 0], [np.inf, 0, 0], [1e30, 0, 0]
    points[-5:] = transform_points(invert_transform(T), GRID.index_to_center(np.array([[0, 0, 0], [31, 23, 7], [3, 4, 5],
                                                                                         [31, 0, 7], [0, 23, 0]])))
    out = np.zeros(int(np.prod(GRID.shape)) + 1, bool)
    mark_points(points, T, *grid_args(GRID), out)
    out = out[:-1]
    idx, inside = GRID.point_to_index(transform_points(T, points[3:]))
    assert 0.05 < inside.mean() < 0.5
    expected = np.zeros(GRID.shape, bool)
    expected[tuple(idx[inside].T)] = True
    assert np.array_equal(out.reshape(GRID.shape), expected)
    assert out.reshape(GRID.shape)[31, 23, 7] and out.reshape(GRID.shape)[0, 23, 0]  # the last points, past the blocks


def test_first_hit_lookup_is_the_or_over_frames_in_any_order():
    rng = np.random.default_rng(2)
    n_voxels = int(np.prod(GRID.shape))
    grids = [rng.random(n_voxels) < p for p in (0.05, 0.3, 0.0)]
    bits = np.stack([np.packbits(g) for g in grids])
    transforms = np.stack([np.eye(4), QUARTER, make_transform(yaw_matrix(1.1), [0.2, 0.1, 0.0])])
    points = rng.uniform(-4, 4, size=(3000, 3)) * [1, 0.75, 0.25]
    expected = np.zeros(len(points), bool)
    for T, g in zip(transforms, grids):
        idx, inside = GRID.point_to_index(transform_points(T, points))
        expected |= inside & g[np.ravel_multi_index(idx.T, GRID.shape)]
    for order in ([0, 1, 2], [2, 1, 0], [1, 0, 2]):
        out = np.zeros(len(points), bool)
        any_bit_set(points, transforms[order], bits[order], *grid_args(GRID), out)
        assert np.array_equal(out, expected)
    assert 0 < expected.sum() < len(points)


def test_flat_voxels_are_the_point_to_index_voxels_on_and_around_every_boundary():
    rng = np.random.default_rng(3)
    edges = [np.arange(lo, hi + 1e-9, GRID.voxel_size) for lo, hi in
             ((GRID.x_min, GRID.x_max), (GRID.y_min, GRID.y_max), (GRID.z_min, GRID.z_max))]
    on_edges = np.stack([rng.choice(e, 3000) + rng.choice([0.0, 1e-12, -1e-12, 0.1], 3000) for e in edges], axis=1)
    wide = rng.uniform(-6, 6, size=(3000, 3))
    points = np.concatenate([on_edges, wide, [[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf]]])
    index, inside = GRID.point_to_index(points)
    expected = np.where(inside, np.ravel_multi_index(index.T, GRID.shape), -1)
    got = flat_voxels(points, *grid_args(GRID))
    assert 0 < inside.sum() < len(points) - 3
    assert np.array_equal(got, expected)
