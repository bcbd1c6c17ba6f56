"""The normal matrix G^T G + ridge of a sparse least-squares design (numba kernels, one thread).

scipy's sparse-sparse product forms G^T G in two passes (a symbolic one for the sizes, then the
values) after transposing G, and computes both triangles. Here the upper triangle is accumulated
in one pass, each design row contributing the products of its entries at or right of the
diagonal column (float64 sums, rounded to float32 once), and then mirrored. Sums run in a fixed
order, so the result is identical run to run.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

INITIAL_ROW_CAPACITY = 96
"""Entries per matrix row reserved up front by `_gram_upper` (the buffers double when exceeded)."""


@numba.njit(cache=True)
def _column_positions(indptr: np.ndarray, indices: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The design's entries column by column: (column pointers (n + 1,), row of each entry, its
    position in the CSR arrays), rows ascending within a column."""
    colptr = np.zeros(n + 1, dtype=np.int64)
    for k in range(len(indices)):
        colptr[indices[k] + 1] += 1
    for col in range(n):
        colptr[col + 1] += colptr[col]
    fill = colptr[:-1].copy()
    rows = np.empty(len(indices), dtype=np.int32)
    positions = np.empty(len(indices), dtype=np.int64)
    for row in range(len(indptr) - 1):
        for k in range(indptr[row], indptr[row + 1]):
            slot = fill[indices[k]]
            rows[slot] = row
            positions[slot] = k
            fill[indices[k]] += 1
    return colptr, rows, positions


@numba.njit(cache=True)
def _gram_upper(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray,
                n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upper triangle of G^T G for G in CSR with sorted rows: (indptr (n + 1,) int64, column ids
    int32 ascending per row, float32 values)."""
    colptr, rows, positions = _column_positions(indptr, indices, n)
    accumulator = np.zeros(n, dtype=np.float64)
    seen = np.full(n, -1, dtype=np.int64)
    capacity = max(INITIAL_ROW_CAPACITY * n, 1)
    out_cols = np.empty(capacity, dtype=np.int32)
    out_data = np.empty(capacity, dtype=np.float32)
    out_ptr = np.zeros(n + 1, dtype=np.int64)
    row_cols = np.empty(n, dtype=np.int32)
    for i in range(n):
        count = 0
        for e in range(colptr[i], colptr[i + 1]):
            r, k = rows[e], positions[e]
            a = np.float64(data[k])
            for k2 in range(k, indptr[r + 1]):  # sorted row: columns >= i from position k on
                j = indices[k2]
                if seen[j] != i:
                    seen[j] = i
                    accumulator[j] = 0.0
                    row_cols[count] = j
                    count += 1
                accumulator[j] += a * data[k2]
        start = out_ptr[i]
        while start + count > capacity:
            capacity *= 2
            grown_cols = np.empty(capacity, dtype=np.int32)
            grown_data = np.empty(capacity, dtype=np.float32)
            grown_cols[:start] = out_cols[:start]
            grown_data[:start] = out_data[:start]
            out_cols, out_data = grown_cols, grown_data
        cols = np.sort(row_cols[:count])
        for m in range(count):
            out_cols[start + m] = cols[m]
            out_data[start + m] = accumulator[cols[m]]
        out_ptr[i + 1] = start + count
    return out_ptr, out_cols[:out_ptr[n]].copy(), out_data[:out_ptr[n]].copy()


@numba.njit(cache=True)
def _mirror(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The full symmetric CSR (int64 row pointers, column ids ascending per row) of the matrix
    whose upper triangle (diagonal included, sorted rows) is the given CSR."""
    n = len(indptr) - 1
    counts = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        counts[i + 1] += indptr[i + 1] - indptr[i]
        for k in range(indptr[i], indptr[i + 1]):
            if indices[k] != i:
                counts[indices[k] + 1] += 1
    full_ptr = np.cumsum(counts)
    fill = full_ptr[:-1].copy()
    full_cols = np.empty(full_ptr[n], dtype=np.int32)
    full_data = np.empty(full_ptr[n], dtype=data.dtype)
    for i in range(n):  # row j's entries left of the diagonal arrive in ascending column order i
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if j != i:
                full_cols[fill[j]] = i
                full_data[fill[j]] = data[k]
                fill[j] += 1
    for i in range(n):
        for k in range(indptr[i], indptr[i + 1]):
            full_cols[fill[i]] = indices[k]
            full_data[fill[i]] = data[k]
            fill[i] += 1
    return full_ptr, full_cols, full_data


def gram(design: sp.csr_matrix, ridge: sp.spmatrix) -> sp.csr_matrix:
    """G^T G + ridge (float32 CSR, column ids ascending per row) of the float32 CSR design G
    (n columns; its rows get sorted in place) and a symmetric n x n `ridge`."""
    design.sort_indices()
    n = design.shape[1]
    indptr, indices, data = _gram_upper(design.indptr.astype(np.int64), design.indices, design.data, n)
    upper = sp.csr_matrix((data, indices, indptr), shape=(n, n)) + sp.triu(ridge, format="csr").astype(np.float32)
    upper.sort_indices()
    full_ptr, full_cols, full_data = _mirror(upper.indptr.astype(np.int64), upper.indices, upper.data)
    index_type = np.int32 if full_ptr[-1] < 2**31 else np.int64
    return sp.csr_matrix((full_data, full_cols.astype(index_type), full_ptr.astype(index_type)), shape=(n, n))
