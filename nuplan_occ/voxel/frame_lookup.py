"""Points moved rigidly into a grid's frame and looked up there (numba kernels).

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
from nuplan_occ.rays.traversal import grid_args


@numba.njit(cache=True, inline="always")
def moved_voxel(points, n, T, lower, voxel_size, shape):
    """int32 flat index of the voxel holding T p for p = points[n] (-1 outside the grid or not finite), without
    branches (in a loop over points it vectorizes; AVX2 converts four doubles to int32 at once)."""
    x, y, z = points[n, 0], points[n, 1], points[n, 2]
    ux = ((((T[0, 0] * x + T[0, 1] * y) + T[0, 2] * z) + T[0, 3]) - lower[0]) / voxel_size
    uy = ((((T[1, 0] * x + T[1, 1] * y) + T[1, 2] * z) + T[1, 3]) - lower[1]) / voxel_size
    uz = ((((T[2, 0] * x + T[2, 1] * y) + T[2, 2] * z) + T[2, 3]) - lower[2]) / voxel_size
    inside = (ux >= 0.0) & (ux < shape[0]) & (uy >= 0.0) & (uy < shape[1]) & (uz >= 0.0) & (uz < shape[2])
    v = (np.int32(ux) * np.int32(shape[1]) + np.int32(uy)) * np.int32(shape[2]) + np.int32(uz)
    return v if inside else np.int32(-1)


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


POINT_BLOCK = 16
"""`mark_points` moves this many points at a time in a branch-free (vectorized) run."""


@numba.njit(cache=True)
def mark_points(points, T, lower, voxel_size, shape, out):
    """out[v] = True for the voxel v holding T p of every point p of points (N, 3), m (`moved_voxel`'s
    arithmetic); out: a flat bool grid of fewer than 2^31 voxels followed by one spare element, which the points
    outside the grid set (so the marking needs no branch). The voxels of POINT_BLOCK points are computed in one
    branch-free run, then marked."""
    flat = np.empty(POINT_BLOCK, np.int32)
    spare = np.int32(out.shape[0] - 1)
    whole = points.shape[0] // POINT_BLOCK * POINT_BLOCK
    for start in range(0, whole, POINT_BLOCK):
        for k in range(POINT_BLOCK):
            v = moved_voxel(points, start + k, T, lower, voxel_size, shape)
            flat[k] = v if v >= 0 else spare
        for k in range(POINT_BLOCK):
            out[flat[k]] = True
    for n in range(whole, points.shape[0]):
        v = moved_voxel(points, n, T, lower, voxel_size, shape)
        out[v if v >= 0 else spare] = True


@numba.njit(cache=True)
def any_bit_set(points, transforms, bits, lower, voxel_size, shape, out):
    """out[n] = True where, for some f, the voxel holding transforms[f] p of point p = points[n] is set in
    bits[f] (packed bits of a flat grid); transforms (F, 4, 4), bits (F, n_bytes) uint8, out (N,) bool.
    The frames are tried in order and a point stops at the first whose bit is set."""
    for n in range(points.shape[0]):
        for f in range(transforms.shape[0]):
            v = moved_voxel(points, n, transforms[f], lower, voxel_size, shape)
            if v >= 0 and (bits[f, v >> 3] >> (7 - (v & 7))) & 1:
                out[n] = True
                break
