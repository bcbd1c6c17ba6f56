"""The kernels behind pose refinement against exact answers: tracked nearest neighbours against fresh kd-tree
queries, PCA normals against exact planes and Open3D, voxel reductions against brute force."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.aggregate import voxel_first_indices
from nuplan_occ.points.knn import KdTree
from nuplan_occ.points.plane_normals import LazyNormals, pca_normals
from nuplan_occ.registration.point_to_plane import normal_equations
from nuplan_occ.registration.tracked_nearest import TrackedNearest
from nuplan_occ.points.voxel_reduce import (KeyIndex, KeySet, accumulate, first_of_each_key, group_means, voxel_centroids,
                                          voxel_keys)


def test_tracked_nearest_equals_fresh_queries_while_points_move():
    rng = np.random.default_rng(0)
    target = rng.uniform(-5, 5, (4000, 3))
    source = rng.uniform(-6, 6, (1500, 3))
    tree = cKDTree(target)
    nearest = TrackedNearest(KdTree(target), len(source), margin_m=0.1)
    # an ICP-like sequence: big steps first, then ever smaller ones, with shrinking bounds
    for step, bound in [(0.3, 1.5), (0.1, 1.5), (0.02, 0.6), (0.0, 0.6), (0.005, 0.25), (1e-4, 0.25), (1e-6, 0.25)]:
        R = Rotation.from_rotvec(rng.normal(size=3) * step / 10).as_matrix()
        source = source @ R.T + rng.normal(size=3) * step
        distance, index = tree.query(source, distance_upper_bound=bound)
        expected = np.where(np.isfinite(distance), index, -1)
        np.testing.assert_array_equal(nearest.query(source, bound), expected)
    assert nearest.queried < 3 * len(source)  # 7 calls, most points answered from memory


def test_kd_tree_queries_equal_scipy_within_a_bound():
    rng = np.random.default_rng(3)
    spread = rng.normal(size=(3000, 3)) * [5.0, 5.0, 0.3]
    queries = rng.uniform(-8, 8, (2000, 3))
    for target in (spread, np.vstack([spread, np.repeat(spread[:20], 3, axis=0)])):  # then with exact ties
        ours, scipy_tree = KdTree(target), cKDTree(target)
        for k, bound in ((1, np.inf), (2, 0.4), (20, 1.0), (5, 0.0)):
            d, i = ours.query(queries, k=k, distance_upper_bound=bound)
            d_ref, i_ref = scipy_tree.query(queries, k=k, distance_upper_bound=bound)
            np.testing.assert_array_equal(d, d_ref.reshape(len(queries), k))
            if len(target) == len(spread):  # a tie may pick another of the equally distant points
                np.testing.assert_array_equal(i, i_ref.reshape(len(queries), k))
        assert (ours.query(queries, k=2, distance_upper_bound=0.4)[1] == len(target)).any()


def test_pca_normals_of_exact_planes_and_open3d():
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-2, 2, (2, 3000))
    normal = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    a = np.cross(normal, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    plane = u[:, None] * a + v[:, None] * b + 7.0
    got = LazyNormals(KdTree(plane), radius_m=1.0, max_nn=20).of(np.arange(0, 3000, 7))
    np.testing.assert_allclose(np.abs(got @ normal), 1.0, atol=1e-9)

    cloud = rng.normal(size=(2000, 3)) * [3.0, 1.0, 0.2]
    o3d_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    o3d_cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.8, max_nn=20))
    lazy = LazyNormals(KdTree(cloud), radius_m=0.8, max_nn=20)
    ours = lazy.of(np.r_[np.arange(2000)[::-1], 5, 5])[:2000][::-1]
    cosine = np.abs(np.sum(ours * np.asarray(o3d_cloud.normals), axis=1))
    assert np.quantile(cosine, 0.99) > 1 - 1e-9 and lazy.known.all()

    isolated = pca_normals(np.zeros((2, 3)), np.array([[0, 1, 2, 2]]))  # two neighbours only
    np.testing.assert_array_equal(isolated, [[0.0, 0.0, 1.0]])


def test_voxel_reductions_against_brute_force():
    rng = np.random.default_rng(2)
    points = np.round(rng.uniform(-3, 3, (5000, 3)), 2)  # many points share voxels, some lie on faces
    cells = np.floor(points / 0.5).astype(np.int64)
    unique, first, inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    np.testing.assert_array_equal(voxel_first_indices(points, 0.5), np.sort(first))
    expected = np.stack([points[inverse.ravel() == c].mean(axis=0) for c in range(len(unique))])
    np.testing.assert_allclose(voxel_centroids(points, 0.5), expected, atol=1e-12)  # key order = index order
    counts = np.bincount(inverse.ravel())
    np.testing.assert_allclose(voxel_centroids(points, 0.5, min_count=5), expected[counts >= 5], atol=1e-12)
    assert 0 < (counts >= 5).sum() < len(counts)  # the gate drops some voxels and keeps others
    assert len(voxel_centroids(np.zeros((0, 3)), 0.5)) == 0 and len(voxel_first_indices(np.zeros((0, 3)), 0.5)) == 0
    rng_keys = np.r_[rng.integers(-2**62, 2**62, 3000), rng.integers(-20, 20, 3000)]  # hash collisions, repeats
    np.testing.assert_array_equal(first_of_each_key(rng_keys), np.sort(np.unique(rng_keys, return_index=True)[1]))
    growing, bounds = KeySet(), [0, 7, 7, 500, 2100, 6000]  # batches that grow the table, and an empty one
    batches = [bounds[i] + growing.new(rng_keys[bounds[i]:bounds[i + 1]]) for i in range(len(bounds) - 1)]
    np.testing.assert_array_equal(np.concatenate(batches), first_of_each_key(rng_keys))
    queries = np.r_[rng_keys[::7], rng.integers(-2**62, 2**62, 2000), np.arange(-40, 40)]
    expected = np.isin(queries, rng_keys)
    assert 0 < expected.sum() < len(queries)  # members and strangers, colliding slots among them
    np.testing.assert_array_equal(growing.holds(queries), expected)
    assert not KeySet().holds(np.array([0, 5])).any()
    with pytest.raises(PointInputError, match="beyond"):
        voxel_keys(np.array([[3e5, 0.0, 0.0]]), 0.2)


def test_key_index_numbers_keys_in_order_of_first_occurrence():
    rng = np.random.default_rng(4)
    keys = np.r_[rng.integers(-2**62, 2**62, 3000), rng.integers(-20, 20, 3000)]  # hash collisions, repeats
    index = KeyIndex(keys)
    np.testing.assert_array_equal(index.keys, keys[first_of_each_key(keys)])
    np.testing.assert_array_equal(index.keys[index.ids], keys)
    assert len(KeyIndex(np.zeros(0, np.int64)).keys) == 0
    values = rng.normal(size=(len(keys), 3))
    expected = np.stack([values[index.ids == g].mean(axis=0) for g in range(len(index.keys))])
    np.testing.assert_allclose(group_means(index.ids, values, len(index.keys)), expected, atol=1e-12)
    growing, bounds = KeyIndex(), [0, 7, 7, 500, 2100, 6000]  # batches that grow the table, and an empty one
    batches = [growing.add(keys[bounds[i]:bounds[i + 1]]) for i in range(len(bounds) - 1)]
    np.testing.assert_array_equal(np.concatenate(batches), index.ids)
    np.testing.assert_array_equal(growing.keys, index.keys)
    sums, counts = np.zeros((len(index.keys), 3)), np.zeros(len(index.keys))
    accumulate(index.ids, values, 1.0, sums, counts)
    np.testing.assert_allclose(sums / counts[:, None], expected, atol=1e-12)
    accumulate(index.ids[:3000], values[:3000], -1.0, sums, counts)  # take the first half away again
    rest = np.isin(np.arange(len(counts)), index.ids[3000:])
    np.testing.assert_array_equal(counts, np.bincount(index.ids[3000:], minlength=len(counts)))
    assert not sums[~rest].any()  # emptied groups are exactly 0


def test_point_to_plane_normal_equations_match_the_dense_formula():
    rng = np.random.default_rng(6)
    target = rng.uniform(-10, 10, (500, 3))
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    moved = target[rng.integers(0, 500, 800)] + rng.normal(size=(800, 3)) * 0.1
    match = np.where(rng.random(800) < 0.8, rng.integers(0, 500, 800), -1)
    A, b = normal_equations(moved, match, target, normals, 0.15)
    src = np.flatnonzero(match >= 0)
    p, q, n = moved[src], target[match[src]], normals[match[src]]
    r = np.sum((p - q) * n, axis=1)
    w = np.where(np.abs(r) < 0.15, (1 - (r / 0.15) ** 2) ** 2, 0.0)
    J = np.hstack([np.cross(p, n), n])
    assert 0 < np.count_nonzero(w) < len(src)  # some residuals beyond the kernel
    np.testing.assert_allclose(A, J.T @ (w[:, None] * J), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b, J.T @ (w * r), rtol=1e-12, atol=1e-12)
