"""Points moved rigidly into a grid's frame and looked up there (numba kernels, one point at a time).

A point p (metres) is moved by a 4x4 rigid transform T as q_i = ((T_i0 p_0 + T_i1 p_1) + T_i2 p_2) + T_i3,
in that order, in IEEE double precision: the result does not depend on the machine's BLAS (numpy's
`transform_points` may differ from it in the last bit). q lies in voxel floor((q - lower) / voxel_size) of
the grid when that index is within [0, shape) on every axis; flat voxel indices are C order over (X, Y, Z).
Packed bits are np.packbits of a flat grid (big-endian bit order within a byte).
"""

from __future__ import annotations

import numba
import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.voxel.traversal import grid_args


@numba.njit(cache=True)
def moved_voxel(p, T, lower, voxel_size, shape):
    """Flat index of the voxel holding T p (-1 outside the grid or not finite)."""
    flat = 0
    for i in range(3):
        q = ((T[i, 0] * p[0] + T[i, 1] * p[1]) + T[i, 2] * p[2]) + T[i, 3]
        u = (q - lower[i]) / voxel_size
        if not (u >= 0.0 and u < shape[i]):
            return -1
        flat = flat * shape[i] + int(u)
    return flat


@numba.njit(cache=True)
def flat_voxels(points, lower, voxel_size, shape):
    """(N,) int64: the flat index of the voxel holding each point of points (N, 3), in the grid's own frame (m),
    -1 outside the grid or not finite (the voxels of `GridSpec.point_to_index`, in one pass)."""
    out = np.empty(points.shape[0], np.int64)
    for n in range(points.shape[0]):
        flat = 0
        for i in range(3):
            u = (points[n, i] - lower[i]) / voxel_size
            if not (u >= 0.0 and u < shape[i]):
                flat = -1
                break
            flat = flat * shape[i] + int(u)
        out[n] = flat
    return out


def point_voxels(points: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(N,) int64: `flat_voxels` of points (N, 3), metres in the grid's own (ego) frame, on `grid`."""
    return flat_voxels(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3), *grid_args(grid))


@numba.njit(cache=True)
def mark_points(points, T, lower, voxel_size, shape, window_lo, window_hi, out):
    """out[v] = True for the voxel v holding T p of every point p of points (N, 3) inside the axis-aligned
    window [window_lo, window_hi] (3,) of their own frame (m); out: flat bool grid. The window must hold the
    grid's box moved there: the points outside it, which cannot land in the grid, are skipped unmoved."""
    for n in range(points.shape[0]):
        x, y, z = points[n, 0], points[n, 1], points[n, 2]
        if (x < window_lo[0] or x > window_hi[0] or y < window_lo[1] or y > window_hi[1]
                or z < window_lo[2] or z > window_hi[2]):
            continue
        v = moved_voxel(points[n], T, lower, voxel_size, shape)
        if v >= 0:
            out[v] = True


@numba.njit(cache=True)
def any_bit_set(points, transforms, bits, lower, voxel_size, shape, out):
    """out[n] = True where, for some f, the voxel holding transforms[f] p of point p = points[n] is set in
    bits[f] (packed bits of a flat grid); transforms (F, 4, 4), bits (F, n_bytes) uint8, out (N,) bool.
    The frames are tried in order and a point stops at the first whose bit is set."""
    for n in range(points.shape[0]):
        for f in range(transforms.shape[0]):
            v = moved_voxel(points[n], transforms[f], lower, voxel_size, shape)
            if v >= 0 and (bits[f, v >> 3] >> (7 - (v & 7))) & 1:
                out[n] = True
                break
