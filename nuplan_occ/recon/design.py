"""Rows of the NKSR-lite least-squares design (numba kernels, one thread).

A query point u (level-0 voxel units, relative to the lattice anchor) touches, at every level of
the hierarchy, the 27 basis functions around its voxel (`basis`); its design row holds the ones
present in the hierarchy, level by level, each level's in `basis.OFFSETS` order. The kernel
evaluates the B-spline factors and looks the coefficient ids up in the flat index volumes
(`hierarchy.FlatLevels`) point by point, without the (K, 27, 3) temporaries of the torch version.
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


@numba.njit(cache=True)
def _rows(u: np.ndarray, scale: np.ndarray, gradient: bool, volumes: np.ndarray, starts: np.ndarray,
          shapes: np.ndarray, los: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR (int64 row pointers, int32 column ids, float32 values) of the K value rows, or of the
    3K gradient rows (x rows, then y, then z), of the queries u (K, 3) scaled by scale (K,)."""
    k = len(u)
    blocks = 3 if gradient else 1
    width = 27 * len(sizes)
    ids = np.empty((k, width), dtype=np.int32)
    terms = np.empty((k, width, blocks), dtype=np.float64)
    counts = np.zeros(k, dtype=np.int64)
    b = np.empty((3, 3))
    db = np.empty((3, 3))
    base = np.empty(3, dtype=np.int64)
    for q in range(k):
        c = 0
        for level in range(len(sizes)):
            size = sizes[level]
            for axis in range(3):
                v = u[q, axis] / size
                cell = np.floor(v)
                base[axis] = np.int64(cell) - los[level, axis]
                f = _factors(v - cell - 0.5)
                for o in range(3):
                    b[axis, o] = f[o]
                    db[axis, o] = f[3 + o] / size
            nx, ny, nz = shapes[level, 0], shapes[level, 1], shapes[level, 2]
            for ox in range(3):
                i = base[0] + ox - 1
                for oy in range(3):
                    j = base[1] + oy - 1
                    for oz in range(3):
                        m = base[2] + oz - 1
                        if i < 0 or i >= nx or j < 0 or j >= ny or m < 0 or m >= nz:
                            continue
                        found = volumes[starts[level] + (i * ny + j) * nz + m]
                        if found < 0:
                            continue
                        ids[q, c] = found
                        if gradient:
                            terms[q, c, 0] = db[0, ox] * b[1, oy] * b[2, oz] * scale[q]
                            terms[q, c, 1] = b[0, ox] * db[1, oy] * b[2, oz] * scale[q]
                            terms[q, c, 2] = b[0, ox] * b[1, oy] * db[2, oz] * scale[q]
                        else:
                            terms[q, c, 0] = b[0, ox] * b[1, oy] * b[2, oz] * scale[q]
                        c += 1
        counts[q] = c
    indptr = np.zeros(blocks * k + 1, dtype=np.int64)
    for block in range(blocks):
        for q in range(k):
            indptr[block * k + q + 1] = indptr[block * k + q] + counts[q]
    indices = np.empty(indptr[-1], dtype=np.int32)
    data = np.empty(indptr[-1], dtype=np.float32)
    for block in range(blocks):
        for q in range(k):
            start = indptr[block * k + q]
            for c in range(counts[q]):
                indices[start + c] = ids[q, c]
                data[start + c] = terms[q, c, block]
    return indptr, indices, data


def design_rows(levels: FlatLevels, num_unknowns: int, u: torch.Tensor, row_scale: torch.Tensor,
                gradient: bool) -> sp.csr_matrix:
    """Rows sqrt(w) * basis values (K rows) or sqrt(w) * basis gradients (3K rows, x then y then z)
    at query points u (K, 3) float64, level-0 units, with sqrt(w) = row_scale (K,): float32 CSR
    with num_unknowns columns."""
    indptr, indices, data = _rows(u.numpy(), row_scale.to(torch.float64).numpy(), gradient, levels.volumes,
                                  levels.starts, levels.shapes, levels.los, levels.sizes)
    index_type = np.int32 if indptr[-1] < 2**31 else np.int64
    return sp.csr_matrix((data, indices.astype(index_type), indptr.astype(index_type)),
                         shape=(len(indptr) - 1, num_unknowns))
