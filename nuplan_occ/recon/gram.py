"""The normal matrix G^T G + ridge of a sparse least-squares design (numba kernels, one thread).

scipy's sparse-sparse product forms G^T G in two passes (a symbolic one for the sizes, then the
values) after transposing G, and computes both triangles. Here the upper triangle is accumulated
in one pass (float64 sums, rounded to float32 once), and then mirrored. The design rows of queries in
one level-0 cell share their column list; such rows are grouped, and a group's products at or right
of the diagonal column are summed densely before they are scattered into the matrix row. Sums run in
a fixed order, so the result is identical run to run.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

INITIAL_ROW_CAPACITY = 96
"""Entries per matrix row reserved up front by `_gram_upper` (the buffers double when exceeded)."""


@numba.njit(cache=True)
def _row_groups(indptr: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The design's rows ordered so that rows with identical column lists are adjacent, and the runs of
    identical lists in that order: (row order (R,), group starts (G + 1,) into it). Rows are ordered by
    a hash of their column list (stable); a hash collision only splits a run, never merges lists."""
    rows = len(indptr) - 1
    keys = np.empty(rows, dtype=np.uint64)
    for r in range(rows):
        h = np.uint64(1469598103934665603) ^ np.uint64(indptr[r + 1] - indptr[r])
        for k in range(indptr[r], indptr[r + 1]):
            h = (h ^ np.uint64(indices[k])) * np.uint64(1099511628211)
        keys[r] = h
    order = np.argsort(keys, kind="mergesort")
    starts = np.empty(rows + 1, dtype=np.int64)
    groups = 0
    for position in range(rows):
        r = order[position]
        same = position > 0
        if same:
            q = order[position - 1]
            length = indptr[r + 1] - indptr[r]
            same = keys[q] == keys[r] and indptr[q + 1] - indptr[q] == length
            k = 0
            while same and k < length:
                same = indices[indptr[q] + k] == indices[indptr[r] + k]
                k += 1
        if not same:
            starts[groups] = position
            groups += 1
    starts[groups] = rows
    return order, starts[:groups + 1].copy()


@numba.njit(cache=True)
def _gram_upper(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, n: int, ridge_ptr: np.ndarray,
                ridge_cols: np.ndarray, ridge_data: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upper triangle of G^T G + ridge for G in CSR with sorted rows and the ridge in CSR (n x n): (indptr
    (n + 1,) int64, column ids int32 ascending per row, float32 values); the value arrays are views of
    buffers somewhat longer than the matrix.

    Rows sharing a column list (the design rows of queries in one level-0 cell) form a group whose
    contribution to matrix row i is first summed over the group's rows in a dense buffer, then added
    once per column: the scattered additions drop by the group's size."""
    order, starts = _row_groups(indptr, indices)
    groups = len(starts) - 1
    colptr = np.zeros(n + 1, dtype=np.int64)
    for g in range(groups):
        first = order[starts[g]]
        for k in range(indptr[first], indptr[first + 1]):
            colptr[indices[k] + 1] += 1
    for col in range(n):
        colptr[col + 1] += colptr[col]
    fill = colptr[:-1].copy()
    member_group = np.empty(colptr[n], dtype=np.int64)
    member_position = np.empty(colptr[n], dtype=np.int64)
    for g in range(groups):
        first = order[starts[g]]
        for k in range(indptr[first], indptr[first + 1]):
            slot = fill[indices[k]]
            member_group[slot] = g
            member_position[slot] = k - indptr[first]
            fill[indices[k]] += 1
    accumulator = np.zeros(n, dtype=np.float64)
    seen = np.full(n, -1, dtype=np.int64)
    buffer = np.zeros(max(n, 1), dtype=np.float64)
    capacity = max(INITIAL_ROW_CAPACITY * n, 1)
    out_cols = np.empty(capacity, dtype=np.int32)
    out_data = np.empty(capacity, dtype=np.float32)
    out_ptr = np.zeros(n + 1, dtype=np.int64)
    row_cols = np.empty(n, dtype=np.int32)
    for i in range(n):
        count = 0
        for e in range(colptr[i], colptr[i + 1]):
            g, a = member_group[e], member_position[e]
            first = order[starts[g]]
            width = indptr[first + 1] - indptr[first] - a
            out = buffer[:width]
            out[:] = 0.0
            for position in range(starts[g], starts[g + 1]):
                head = indptr[order[position]] + a
                row = data[head:head + width]
                x = np.float64(row[0])
                for b in range(width):
                    out[b] += x * row[b]
            cols_g = indices[indptr[first] + a:indptr[first] + a + width]
            for b in range(width):
                j = cols_g[b]
                if seen[j] != i:
                    seen[j] = i
                    accumulator[j] = 0.0
                    row_cols[count] = j
                    count += 1
                accumulator[j] += out[b]
        for k in range(ridge_ptr[i], ridge_ptr[i + 1]):  # written out as above: a shared helper doubled the time
            j = ridge_cols[k]
            if j < i:
                continue
            if seen[j] != i:
                seen[j] = i
                accumulator[j] = 0.0
                row_cols[count] = j
                count += 1
            accumulator[j] += ridge_data[k]
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
    return out_ptr, out_cols[:out_ptr[n]], out_data[:out_ptr[n]]


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


def normal_equations(design: list[sp.csr_matrix], targets: np.ndarray,
                     ridge: sp.spmatrix) -> tuple[sp.csr_matrix, np.ndarray]:
    """(G^T G + ridge, G^T y) of the least-squares design G = design[0] (float32 CSR, n columns) with targets
    y (float32), and a symmetric n x n `ridge`: float32 CSR with column ids ascending per row, and float32
    (n,). The design is the largest array of a solve: it is taken out of its list and released before the
    upper triangle is mirrored."""
    design = design.pop()
    rhs = np.asarray(design.T @ targets, dtype=np.float32)
    design.sort_indices()
    n = design.shape[1]
    ridge = sp.csr_matrix(ridge, dtype=np.float64)
    ridge.sort_indices()
    upper = _gram_upper(design.indptr.astype(np.int64), design.indices, design.data, n,
                        ridge.indptr.astype(np.int64), ridge.indices, ridge.data)
    del design
    full_ptr, full_cols, full_data = _mirror(*upper)
    del upper
    index_type = np.int32 if full_ptr[-1] < 2**31 else np.int64
    return (sp.csr_matrix((full_data, full_cols.astype(index_type, copy=False), full_ptr.astype(index_type)),
                          shape=(n, n), copy=False), rhs)
