"""The B-spline basis, the voxel hierarchy and the PCG solver against known truth."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from nuplan_occ.recon.basis import gram_weights, stencil
from nuplan_occ.recon.design import design_matrix
from nuplan_occ.recon.gram import normal_equations
from nuplan_occ.recon.hierarchy import FlatLevels, VoxelHierarchy, dilate, unique_voxels
from nuplan_occ.recon.nksr_lite import ImplicitField, ridge_matrix
from nuplan_occ.recon.pcg import jacobi_pcg, to_torch_csr


def test_basis_is_partition_of_unity_and_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    u = torch.from_numpy(rng.uniform(-10, 10, (500, 3)))
    for size in (1, 2, 4):
        ijk, values, grads = stencil(u, size, gradient=True)
        assert torch.allclose(values.sum(dim=1), torch.ones(len(u), dtype=u.dtype), atol=1e-12)
        assert torch.allclose(grads.sum(dim=1), torch.zeros(len(u), 3, dtype=u.dtype), atol=1e-12)
        eps = 1e-6
        for axis in range(3):
            shifted = u.clone()
            shifted[:, axis] += eps
            ijk2, values2, _ = stencil(shifted, size, gradient=False)
            same = (ijk2 == ijk).all(dim=2).all(dim=1)  # skip queries that crossed a voxel face
            numeric = (values2 - values)[same] / eps
            assert torch.allclose(numeric, grads[same][..., axis], atol=1e-4)


def test_gram_weights_are_the_spline_at_integer_offsets():
    w = gram_weights(torch.float64)
    assert w.shape == (27,)
    assert np.isclose(float(w[13]), 0.75**3)  # centre
    assert np.isclose(float(w[0]), 0.125**3)  # corner neighbour
    assert np.isclose(float(w.sum()), 1.0)


def test_unique_voxels_and_dilate():
    coords = torch.tensor([[3, -1, 2], [0, 0, 0], [3, -1, 2], [-5, 7, 1]])
    uniq, inverse, counts = unique_voxels(coords)
    assert uniq.tolist() == [[-5, 7, 1], [0, 0, 0], [3, -1, 2]]
    assert torch.equal(uniq[inverse], coords)
    assert counts.tolist() == [1, 1, 2]
    assert len(dilate(torch.tensor([[0, 0, 0]]), 2)) == 125


def test_hierarchy_levels_and_lookup():
    occupied = torch.tensor([[0, 0, 0], [1, 0, 0], [7, 3, 2]])
    hierarchy = VoxelHierarchy.build(occupied, 3)
    level0, level1, level2 = hierarchy.levels
    assert len(level0.coords) == 3
    assert level1.size == 2 and level2.size == 4
    assert hierarchy.num_unknowns == 3 + len(level1.coords) + len(level2.coords)
    # every occupied voxel's parent and its 26 neighbours exist at level 1
    parents = torch.div(occupied, 2, rounding_mode="floor")
    assert (level1.ids(parents.unsqueeze(1) + torch.tensor([[-1, -1, -1], [1, 1, 1]])) >= 0).all()
    assert level0.ids(torch.tensor([[7, 3, 2], [2, 0, 0], [100, 0, 0]])).tolist() == [2, -1, -1]


def test_jacobi_pcg_matches_direct_solve():
    rng = np.random.default_rng(1)
    n = 300
    a = sp.random(n, n, density=0.02, random_state=2)
    matrix = (a @ a.T + sp.diags(rng.uniform(1, 5, n))).tocsr()
    rhs = rng.normal(size=n)
    expected = np.linalg.solve(matrix.toarray(), rhs)
    result = jacobi_pcg(to_torch_csr(matrix, torch.float64), torch.from_numpy(matrix.diagonal()),
                        torch.from_numpy(rhs), 1e-10, 1000)
    assert result.relative_residual <= 1e-10
    assert np.allclose(result.x.numpy(), expected, atol=1e-8)


def test_normal_equations_equal_the_sparse_products_with_sorted_symmetric_rows():
    rng = np.random.default_rng(4)
    design = sp.random(400, 120, density=0.05, random_state=5, dtype=np.float32, format="csr")
    design = design[rng.permutation(400)]  # unsorted rows are sorted by `normal_equations`
    targets = rng.normal(size=400).astype(np.float32)
    ridge = sp.random(120, 120, density=0.03, random_state=6)
    ridge = (ridge + ridge.T).tocsr()
    expected = (design.T.astype(np.float64) @ design + ridge).toarray()
    holder = [design.copy()]
    matrix, rhs = normal_equations(holder, targets, ridge)
    assert holder == []
    assert matrix.dtype == np.float32 and matrix.has_sorted_indices
    assert np.allclose(matrix.toarray(), expected, rtol=1e-6, atol=1e-6)
    assert np.allclose(rhs, design.T.astype(np.float64) @ targets, rtol=1e-5, atol=1e-5)
    again, _ = normal_equations([design.copy()], targets, ridge)
    assert (matrix != again).nnz == 0


def test_normal_equations_group_rows_sharing_their_columns_without_changing_the_product():
    rng = np.random.default_rng(8)
    lists = [np.sort(rng.choice(90, size=rng.integers(5, 30), replace=False)) for _ in range(25)]
    picks = rng.integers(0, len(lists), 300)  # 300 rows over 25 column lists, in mixed order
    rows = np.repeat(np.arange(300), [len(lists[p]) for p in picks])
    cols = np.concatenate([lists[p] for p in picks])
    design = sp.csr_matrix((rng.normal(size=len(cols)).astype(np.float32), (rows, cols)), shape=(300, 90))
    ridge = sp.identity(90, format="csr") * 0.01
    expected = (design.T.astype(np.float64) @ design + ridge).toarray()
    matrix, _ = normal_equations([design], np.zeros(300, np.float32), ridge)
    assert np.allclose(matrix.toarray(), expected, rtol=1e-6, atol=1e-6)


def test_design_matrix_holds_the_basis_terms_of_the_hierarchy_part_after_part():
    rng = np.random.default_rng(7)
    occupied = unique_voxels(torch.from_numpy(rng.integers(0, 10, (80, 3))))[0]
    hierarchy = VoxelHierarchy.build(occupied, 3)
    n = hierarchy.num_unknowns
    u = torch.from_numpy(rng.uniform(-1, 11, (300, 3)))
    scale = torch.from_numpy(rng.uniform(0.5, 2, 300))
    expected_values, expected_grads = np.zeros((300, n)), np.zeros((3, 300, n))
    for level in hierarchy.levels:
        ijk, values, grads = stencil(u, level.size, gradient=True)
        ids = level.ids(ijk)
        rows, slots = torch.nonzero(ids >= 0, as_tuple=True)
        np.add.at(expected_values, (rows.numpy(), ids[rows, slots].numpy()), values[rows, slots].numpy())
        for axis in range(3):
            np.add.at(expected_grads[axis], (rows.numpy(), ids[rows, slots].numpy()), grads[rows, slots, axis].numpy())
    levels = FlatLevels.of(hierarchy)
    rows = design_matrix(levels, n, [(u, scale, False), (u[:100], scale[:100], True), (u, scale, False)]).toarray()
    value_rows = expected_values * scale.numpy()[:, None]
    assert np.allclose(rows[:300], value_rows, atol=1e-6)
    assert np.allclose(rows[300:600], (expected_grads[:, :100] * scale.numpy()[None, :100, None]).reshape(300, n),
                       atol=1e-6)
    assert np.allclose(rows[600:], value_rows, atol=1e-6)


def test_design_rows_of_level_subsets_split_the_full_rows_by_level():
    rng = np.random.default_rng(8)
    occupied = unique_voxels(torch.from_numpy(rng.integers(0, 10, (80, 3))))[0]
    hierarchy = VoxelHierarchy.build(occupied, 3)
    n, split = hierarchy.num_unknowns, hierarchy.levels[-1].offset
    u = torch.from_numpy(rng.uniform(-1, 11, (200, 3)))
    parts = [(u, torch.from_numpy(rng.uniform(0.5, 2, 200)), False), (u[:50], torch.ones(50, dtype=torch.float64), True)]
    levels = FlatLevels.of(hierarchy)
    full = design_matrix(levels, n, parts).toarray()
    fine = design_matrix(levels.subset(slice(0, -1)), n, parts).toarray()
    coarse = design_matrix(levels.subset(slice(-1, None)), n, parts).toarray()
    assert np.all(fine[:, split:] == 0) and np.all(coarse[:, :split] == 0)  # ids stay global
    assert np.any(coarse[:, split:] != 0) and np.any(fine[:, :split] != 0)
    assert np.array_equal(fine + coarse, full)


def test_lookup_inside_and_beyond_the_index_volume_agree_with_a_dictionary():
    rng = np.random.default_rng(3)
    occupied = unique_voxels(torch.from_numpy(rng.integers(0, 12, (60, 3))))[0]
    level0 = VoxelHierarchy.build(occupied, 1).levels[0]
    truth = {tuple(c): i for i, c in enumerate(occupied.tolist())}
    near = torch.from_numpy(rng.integers(-3, 15, (200, 3)))  # inside the padded volume: one gather
    far = torch.cat([near, torch.tensor([[-40, 0, 0], [0, 90, 0]])])  # some beyond it: masked lookups
    for queries in (near, far):
        assert level0.ids(queries).tolist() == [truth.get(tuple(q), -1) for q in queries.tolist()]


def test_field_values_are_the_design_rows_times_the_coefficients():
    rng = np.random.default_rng(11)
    occupied = unique_voxels(torch.from_numpy(rng.integers(0, 10, (80, 3))))[0]
    hierarchy = VoxelHierarchy.build(occupied, 3)
    coefficients = torch.from_numpy(rng.normal(size=hierarchy.num_unknowns).astype(np.float32))
    u = torch.from_numpy(rng.uniform(-12, 22, (400, 3)))  # some queries beyond every level's voxels
    levels = FlatLevels.of(hierarchy)
    rows = design_matrix(levels, hierarchy.num_unknowns, [(u, torch.ones(len(u)), False)]).astype(np.float64)
    field = ImplicitField(hierarchy, levels, coefficients, np.zeros(3), 0.25)
    values = field.evaluate(u).numpy()
    assert values.dtype == np.float32
    assert np.allclose(values, rows @ coefficients.numpy().astype(np.float64), atol=1e-5)
    assert np.count_nonzero(values) > 100 and np.count_nonzero(values == 0) > 20


def test_ridge_holds_the_spline_at_every_same_level_neighbour_offset():
    rng = np.random.default_rng(12)
    occupied = unique_voxels(torch.from_numpy(rng.integers(0, 9, (70, 3))))[0]
    hierarchy = VoxelHierarchy.build(occupied, 3)
    ridge = ridge_matrix(hierarchy, 0.25).toarray()
    weights = gram_weights(torch.float32).numpy()
    expected = np.zeros_like(ridge)
    for level in hierarchy.levels:
        coords = level.coords.numpy()
        for a, ca in enumerate(coords):
            for b, cb in enumerate(coords):
                offset = cb - ca
                if np.abs(offset).max() <= 1:
                    expected[level.offset + a, level.offset + b] = weights[(offset[0] + 1) * 9 + (offset[1] + 1) * 3
                                                                           + offset[2] + 1] * np.float32(0.25)
    assert np.array_equal(ridge, expected) and np.array_equal(ridge, ridge.T)
