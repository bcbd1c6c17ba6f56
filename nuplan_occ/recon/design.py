"""Rows of the NKSR-lite least-squares design (numba kernels, one thread).

A query point u (level-0 voxel units, relative to the lattice anchor) touches, at every level of
the hierarchy, the 27 basis functions around its voxel (`basis`); its design row holds the ones
present in the hierarchy, level by level, each level's in `basis.OFFSETS` order. The kernels
evaluate the B-spline factors and look the coefficient ids up in the flat index volumes
(`hierarchy.FlatLevels`) point by point, in two passes: one counting every row's entries, one
writing them into the design's final arrays (no per-query temporaries, no stacking copy).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
import torch

from nuplan_occ.recon.hierarchy import FlatLevels


@numba.njit(cache=True, inline="always")
def _factors(t: float) -> tuple[float, float, float, float, float, float]:
    """b and b' at offsets -1, 0, 1 for the position t in [-0.5, 0.5) inside the own voxel."""
    return (0.5 * (t - 0.5) ** 2, 0.75 - t * t, 0.5 * (t + 0.5) ** 2, t - 0.5, -2.0 * t, t + 0.5)


@numba.njit(cache=True, inline="always")
def _level_factors(u, q, level, los, sizes, b, db, base):
    """Fill b, db (3 axes, 3 offsets) with the basis factors and derivatives of query q at `level`, and base (3,)
    with its voxel relative to the level's index volume."""
    size = sizes[level]
    for axis in range(3):
        v = u[q, axis] / size
        cell = np.floor(v)
        base[axis] = np.int64(cell) - los[level, axis]
        f = _factors(v - cell - 0.5)
        for o in range(3):
            b[axis, o] = f[o]
            db[axis, o] = f[3 + o] / size


@numba.njit(cache=True, inline="always")
def _coefficient_id(volumes, starts, shapes, level, i, j, m):
    """The coefficient id of voxel (i, j, m) of a level's index volume (relative to its lo); -1 when absent or
    outside the volume."""
    nx, ny, nz = shapes[level, 0], shapes[level, 1], shapes[level, 2]
    if i < 0 or i >= nx or j < 0 or j >= ny or m < 0 or m >= nz:
        return -1
    return volumes[starts[level] + (i * ny + j) * nz + m]


@numba.njit(cache=True)
def _query_rows(u, q, scale, gradient, volumes, starts, shapes, los, sizes, b, db, base, count_only,
                heads, indices, data):
    """The entries of query q's row (value) or rows (gradient x, y, z): their number when count_only,
    else written at heads[0] (and heads[1], heads[2] for the gradient rows)."""
    c = 0
    for level in range(len(sizes)):
        _level_factors(u, q, level, los, sizes, b, db, base)
        for ox in range(3):
            for oy in range(3):
                for oz in range(3):
                    found = _coefficient_id(volumes, starts, shapes, level, base[0] + ox - 1, base[1] + oy - 1,
                                            base[2] + oz - 1)
                    if found < 0:
                        continue
                    if not count_only:
                        if gradient:
                            indices[heads[0] + c] = found
                            indices[heads[1] + c] = found
                            indices[heads[2] + c] = found
                            data[heads[0] + c] = db[0, ox] * b[1, oy] * b[2, oz] * scale[q]
                            data[heads[1] + c] = b[0, ox] * db[1, oy] * b[2, oz] * scale[q]
                            data[heads[2] + c] = b[0, ox] * b[1, oy] * db[2, oz] * scale[q]
                        else:
                            indices[heads[0] + c] = found
                            data[heads[0] + c] = b[0, ox] * b[1, oy] * b[2, oz] * scale[q]
                    c += 1
    return c


@numba.njit(cache=True)
def _count(u, gradient, volumes, starts, shapes, los, sizes, counts, first_row):
    """counts[first_row + r] = the entries of the part's r-th row (K rows, or 3K gradient rows: x rows, then
    y, then z)."""
    k = len(u)
    b, db, base = np.empty((3, 3)), np.empty((3, 3)), np.empty(3, dtype=np.int64)
    heads = np.zeros(3, dtype=np.int64)
    none_i, none_d = np.empty(0, dtype=np.int32), np.empty(0, dtype=np.float32)
    for q in range(k):
        c = _query_rows(u, q, u[:, 0], gradient, volumes, starts, shapes, los, sizes, b, db, base, True,
                        heads, none_i, none_d)
        for block in range(3 if gradient else 1):
            counts[first_row + block * k + q] = c


@numba.njit(cache=True)
def _fill(u, scale, gradient, volumes, starts, shapes, los, sizes, indptr, indices, data, first_row):
    """Write the part's rows (see `_count`) at their places in the design's CSR arrays."""
    k = len(u)
    b, db, base = np.empty((3, 3)), np.empty((3, 3)), np.empty(3, dtype=np.int64)
    heads = np.zeros(3, dtype=np.int64)
    for q in range(k):
        for block in range(3 if gradient else 1):
            heads[block] = indptr[first_row + block * k + q]
        _query_rows(u, q, scale, gradient, volumes, starts, shapes, los, sizes, b, db, base, False,
                    heads, indices, data)


@numba.njit(cache=True)
def field_values(u, coefficients, volumes, starts, shapes, los, sizes):
    """(K,) float32: the field sum_j coefficients[j] B_j(u) at query points u (K, 3) float64 (level-0 units),
    summed in float64 level by level, each level's 27 terms in `basis.OFFSETS` order and added to the total
    as one level sum; coefficients (n,) float32 (see `_query_rows` for the other arguments)."""
    out = np.empty(len(u), dtype=np.float32)
    b, db = np.empty((3, 3)), np.empty((3, 3))
    base = np.empty(3, dtype=np.int64)
    for q in range(len(u)):
        total = 0.0
        for level in range(len(sizes)):
            _level_factors(u, q, level, los, sizes, b, db, base)
            level_sum = 0.0
            for ox in range(3):
                for oy in range(3):
                    for oz in range(3):
                        found = _coefficient_id(volumes, starts, shapes, level, base[0] + ox - 1, base[1] + oy - 1,
                                                base[2] + oz - 1)
                        if found >= 0:
                            level_sum += b[0, ox] * b[1, oy] * b[2, oz] * np.float64(coefficients[found])
            total += level_sum
        out[q] = np.float32(total)
    return out


def design_matrix(levels: FlatLevels, num_unknowns: int,
                  parts: list[tuple[torch.Tensor, torch.Tensor, bool]]) -> sp.csr_matrix:
    """The design rows of every part (u, row_scale, gradient), one part after another: at query points u
    (K, 3) float64, level-0 units, sqrt(w) = row_scale (K,) times the basis values (K rows) or, with
    gradient, times the basis gradients (3K rows, x then y then z). float32 CSR with num_unknowns columns."""
    arrays = [(np.ascontiguousarray(u.numpy()), np.ascontiguousarray(scale.to(torch.float64).numpy()), gradient)
              for u, scale, gradient in parts]
    volume_args = (levels.volumes, levels.starts, levels.shapes, levels.los, levels.sizes)
    first_rows = np.cumsum([0] + [len(u) * (3 if gradient else 1) for u, _, gradient in arrays])
    counts = np.zeros(first_rows[-1], dtype=np.int64)
    for (u, _, gradient), first in zip(arrays, first_rows):
        _count(u, gradient, *volume_args, counts, first)
    indptr = np.concatenate([[0], np.cumsum(counts)])
    del counts
    indices = np.empty(indptr[-1], dtype=np.int32)
    data = np.empty(indptr[-1], dtype=np.float32)
    for (u, scale, gradient), first in zip(arrays, first_rows):
        _fill(u, scale, gradient, *volume_args, indptr, indices, data, first)
    index_type = np.int32 if indptr[-1] < 2**31 else np.int64
    return sp.csr_matrix((data, indices, indptr.astype(index_type)), shape=(len(indptr) - 1, num_unknowns),
                         copy=False)
