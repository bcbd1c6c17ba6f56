"""Surface normals of a point cloud by principal component analysis of each point's nearest neighbours,
computed on demand for the points that need one (ICP uses the normals of the map points it matched only).

The normal of point i is the eigenvector of the smallest eigenvalue of the covariance of its `max_nn`
nearest points within `radius_m` (itself included), the neighbourhood of Open3D's
`estimate_normals(KDTreeSearchParamHybrid(radius, max_nn))`; fewer than 3 neighbours give (0, 0, 1), as
there. The sign is arbitrary (point-to-plane ICP does not depend on it). Points and normals share one
frame; metres.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from nuplan_occ.points.knn import KdTree


@numba.njit(cache=True)
def smallest_eigenvector(c00: float, c01: float, c02: float, c11: float, c12: float, c22: float
                         ) -> tuple[float, float, float]:
    """Unit eigenvector of the smallest eigenvalue of the symmetric 3x3 matrix [[c00, c01, c02], [c01, c11,
    c12], [c02, c12, c22]] (closed form: trigonometric eigenvalue, then the longest cross product of two rows
    of c - lambda I); (0, 0, 1) when c is a multiple of the identity."""
    scale = max(abs(c00), abs(c01), abs(c02), abs(c11), abs(c12), abs(c22))
    if scale == 0.0:
        return 0.0, 0.0, 1.0
    a00, a01, a02, a11, a12, a22 = c00 / scale, c01 / scale, c02 / scale, c11 / scale, c12 / scale, c22 / scale
    q = (a00 + a11 + a22) / 3.0
    p = math.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * (a01 ** 2 + a02 ** 2 + a12 ** 2)) / 6.0)
    if p == 0.0:
        return 0.0, 0.0, 1.0
    b00, b11, b22, b01, b02, b12 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p, a01 / p, a02 / p, a12 / p
    half_det = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    phi = math.acos(min(max(half_det, -1.0), 1.0)) / 3.0
    smallest = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    m00, m11, m22 = a00 - smallest, a11 - smallest, a22 - smallest
    # rows r0 = (m00, a01, a02), r1 = (a01, m11, a12), r2 = (a02, a12, m22); their pairwise cross products
    x0, y0, z0 = a01 * a12 - a02 * m11, a02 * a01 - m00 * a12, m00 * m11 - a01 * a01  # r0 x r1
    x1, y1, z1 = a01 * m22 - a02 * a12, a02 * a02 - m00 * m22, m00 * a12 - a01 * a02  # r0 x r2
    x2, y2, z2 = m11 * m22 - a12 * a12, a12 * a02 - a01 * m22, a01 * a12 - m11 * a02  # r1 x r2
    n0, n1, n2 = x0 * x0 + y0 * y0 + z0 * z0, x1 * x1 + y1 * y1 + z1 * z1, x2 * x2 + y2 * y2 + z2 * z2
    if n0 >= n1 and n0 >= n2 and n0 > 0.0:
        r = 1.0 / math.sqrt(n0)
        return x0 * r, y0 * r, z0 * r
    if n1 >= n2 and n1 > 0.0:
        r = 1.0 / math.sqrt(n1)
        return x1 * r, y1 * r, z1 * r
    if n2 > 0.0:
        r = 1.0 / math.sqrt(n2)
        return x2 * r, y2 * r, z2 * r
    return 0.0, 0.0, 1.0


@numba.njit(cache=True)
def pca_normals(points: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(n, 3) normals from neighbours (n, k) int64 indices into points (m, 3); an index >= m is no
    neighbour (the kd-tree's fill value). Fewer than 3 neighbours give (0, 0, 1)."""
    n, k = neighbours.shape
    m = len(points)
    normals = np.empty((n, 3))
    for i in range(n):
        count = 0
        mx = my = mz = 0.0
        for j in range(k):
            t = neighbours[i, j]
            if t < m:
                mx += points[t, 0]
                my += points[t, 1]
                mz += points[t, 2]
                count += 1
        if count < 3:
            normals[i, 0], normals[i, 1], normals[i, 2] = 0.0, 0.0, 1.0
            continue
        mx, my, mz = mx / count, my / count, mz / count
        c00 = c01 = c02 = c11 = c12 = c22 = 0.0
        for j in range(k):
            t = neighbours[i, j]
            if t < m:
                dx, dy, dz = points[t, 0] - mx, points[t, 1] - my, points[t, 2] - mz
                c00 += dx * dx
                c01 += dx * dy
                c02 += dx * dz
                c11 += dy * dy
                c12 += dy * dz
                c22 += dz * dz
        normals[i, 0], normals[i, 1], normals[i, 2] = smallest_eigenvector(c00, c01, c02, c11, c12, c22)
    return normals


class LazyNormals:
    """Normals of the points (m, 3) of `tree` (nuplan_occ.points.knn.KdTree), each computed the first time it is asked for."""

    def __init__(self, tree: KdTree, radius_m: float, max_nn: int):
        self.tree = tree
        self.radius_m = radius_m
        self.max_nn = max_nn
        self.normals = np.zeros((tree.n, 3))
        self.known = np.zeros(tree.n, dtype=bool)

    def ensure(self, indices: np.ndarray) -> None:
        """Compute the normals of the points `indices` (int, any order, repeats allowed) not known yet;
        `normals` (m, 3) then holds them."""
        missing = np.unique(indices[~self.known[indices]])
        if len(missing):
            _, neighbours = self.tree.query(self.tree.data[missing], k=self.max_nn, distance_upper_bound=self.radius_m)
            self.normals[missing] = pca_normals(self.tree.data, neighbours.reshape(len(missing), -1).astype(np.int64))
            self.known[missing] = True

    def adopt(self, indices: np.ndarray, normals: np.ndarray) -> None:
        """Take normals (n, 3) as known for the points `indices` (n,) (e.g. computed earlier for the same
        surface); they are then not computed."""
        self.normals[indices] = normals
        self.known[indices] = True

    def of(self, indices: np.ndarray) -> np.ndarray:
        """(len(indices), 3) normals of the points `indices` (int, any order, repeats allowed)."""
        self.ensure(indices)
        return self.normals[indices]
