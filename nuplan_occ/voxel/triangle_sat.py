"""Exact triangle/voxel overlap on a voxel lattice (numba kernels).

The tests run in "voxel units" of the lattice (u = (p - origin) / voxel_size for a mesh given in metres):
voxel (i, j, k) is the half-open unit cube [i, i+1) x [j, j+1) x [k, k+1).
A voxel is touched iff the closed triangle intersects it. The half-open cube is realised as the closed
cube [i-EPS, i+1-EPS]^3 with EPS = 1e-7 voxel (a lattice shifted by EPS, no gaps between cubes), so a
surface lying on a voxel boundary, or within rounding error of it, touches only the voxel above it (the
convention of `GridSpec.point_to_index`). The test is the separating-axis theorem (13 axes,
Akenine-Moeller's triangle/box overlap) on every voxel of the triangle's bounding box, so a triangle of
any size is voxelized without holes and without being split.
"""

from __future__ import annotations

import math

import numba
import numpy as np

EPS = 1e-7
"""Shift (voxel units) of the closed test cubes [i-EPS, i+1-EPS] that emulates half-open voxels."""

_H = 0.5
_CENTER = _H - EPS  # a voxel's test-cube centre relative to its index


@numba.njit(cache=True, inline="always")
def _min3(a: float, b: float, c: float) -> float:
    return min(min(a, b), c)


@numba.njit(cache=True, inline="always")
def _max3(a: float, b: float, c: float) -> float:
    return max(max(a, b), c)


@numba.njit(cache=True, inline="always")
def _edge_axes_separate(u: np.ndarray, fa: float, fb: float, a: int, b: int) -> bool:
    """Whether the axis e_c x f (c the third axis; components -f_b at a, f_a at b) separates the triangle
    u (3, 3) [vertex, axis] (relative to the cube centre) from the cube of half side _H."""
    p0 = u[0, b] * fa - u[0, a] * fb
    p1 = u[1, b] * fa - u[1, a] * fb
    p2 = u[2, b] * fa - u[2, a] * fb
    r = _H * (abs(fa) + abs(fb))
    return not (_min3(p0, p1, p2) <= r and _max3(p0, p1, p2) >= -r)


@numba.njit(cache=True)
def triangle_overlaps_voxel(tri: np.ndarray, i: int, j: int, k: int, u: np.ndarray) -> bool:
    """Whether the closed triangle tri (3, 3) [vertex, axis] (voxel units) meets the closed cube
    [v-EPS, v+1-EPS]^3 of voxel v = (i, j, k). u: (3, 3) float64 scratch."""
    center = (i + _CENTER, j + _CENTER, k + _CENTER)
    for n in range(3):
        for a in range(3):
            u[n, a] = tri[n, a] - center[a]
    for a in range(3):
        if not (_min3(u[0, a], u[1, a], u[2, a]) <= _H and _max3(u[0, a], u[1, a], u[2, a]) >= -_H):
            return False
    e00, e01, e02 = u[1, 0] - u[0, 0], u[1, 1] - u[0, 1], u[1, 2] - u[0, 2]
    e10, e11, e12 = u[2, 0] - u[0, 0], u[2, 1] - u[0, 1], u[2, 2] - u[0, 2]
    n0, n1, n2 = e01 * e12 - e02 * e11, e02 * e10 - e00 * e12, e00 * e11 - e01 * e10
    dot = n0 * u[0, 0] + n1 * u[0, 1] + n2 * u[0, 2]
    if not abs(dot) <= _H * (abs(n0) + abs(n1) + abs(n2)):
        return False
    for start in range(3):
        stop = (start + 1) % 3
        f0, f1, f2 = u[stop, 0] - u[start, 0], u[stop, 1] - u[start, 1], u[stop, 2] - u[start, 2]
        if (_edge_axes_separate(u, f1, f2, 1, 2) or _edge_axes_separate(u, f2, f0, 2, 0)
                or _edge_axes_separate(u, f0, f1, 0, 1)):
            return False
    return True


@numba.njit(cache=True)
def mark_triangle_voxels(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, voxel_size: float,
                         lo: np.ndarray, out: np.ndarray) -> None:
    """Set out[v - lo] for every voxel v inside the box [lo, lo + out.shape) touched by a triangle.

    vertices (V, 3) float64 and faces (F, 3) int64: the mesh, in a frame where voxel v of the lattice is
    the cube origin + voxel_size * [v, v + 1); it is tested in voxel units u = (p - origin) / voxel_size.
    lo: (3,) int64 lattice index of out[0, 0, 0]; out: (X, Y, Z) bool, updated in place (voxels outside
    the box are skipped). A triangle whose bounding box lies in one voxel (floor(min + EPS) ==
    floor(max + EPS) on every axis) touches it without a test; otherwise each voxel of that box is tested
    (see `triangle_overlaps_voxel`)."""
    tri = np.empty((3, 3))
    u = np.empty((3, 3))
    first = np.empty(3, np.int64)
    last = np.empty(3, np.int64)
    for f in range(faces.shape[0]):
        for n in range(3):
            for a in range(3):
                tri[n, a] = (vertices[faces[f, n], a] - origin[a]) / voxel_size
        single = True
        for a in range(3):
            first[a] = math.floor(_min3(tri[0, a], tri[1, a], tri[2, a]) + EPS)
            last[a] = math.floor(_max3(tri[0, a], tri[1, a], tri[2, a]) + EPS)
            single = single and first[a] == last[a]
            first[a] = max(first[a], lo[a]) - lo[a]
            last[a] = min(last[a], lo[a] + out.shape[a] - 1) - lo[a]
        if single:
            if first[0] <= last[0] and first[1] <= last[1] and first[2] <= last[2]:
                out[first[0], first[1], first[2]] = True
            continue
        for i in range(first[0], last[0] + 1):
            for j in range(first[1], last[1] + 1):
                for k in range(first[2], last[2] + 1):
                    if not out[i, j, k] and triangle_overlaps_voxel(tri, i + lo[0], j + lo[1], k + lo[2], u):
                        out[i, j, k] = True
