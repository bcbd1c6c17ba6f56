"""Normal equations of one Gauss-Newton step of point-to-plane ICP with a Tukey kernel (compiled).

For a source point p (already moved into the map frame) matched to map point q with unit normal n, the
residual is r = (p - q) . n and its Jacobian with respect to a small motion (rotation vector w, then
translation t, applied as p -> R(w) p + t) is J = [p x n, n]. With Tukey weights
w(r) = (1 - (r / c)^2)^2 for |r| < c (else 0), the step x minimises sum w (J x + r)^2, i.e. solves
A x = -b with A = sum w J J^T and b = sum w J r. Frame: the map frame; metres, radians.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def normal_equations(moved: np.ndarray, match: np.ndarray, target: np.ndarray, normals: np.ndarray,
                     tukey_c: float) -> tuple[np.ndarray, np.ndarray]:
    """(A (6, 6), b (6,)) over the source points moved (n, 3) with match[i] >= 0 (the index of their map
    point in target (m, 3) / normals (m, 3)); points with match -1 do not count. Sums in point order."""
    A = np.zeros((6, 6))
    b = np.zeros(6)
    J = np.empty(6)
    for i in range(len(moved)):
        j = match[i]
        if j < 0:
            continue
        px, py, pz = moved[i, 0], moved[i, 1], moved[i, 2]
        nx, ny, nz = normals[j, 0], normals[j, 1], normals[j, 2]
        r = (px - target[j, 0]) * nx + (py - target[j, 1]) * ny + (pz - target[j, 2]) * nz
        if abs(r) >= tukey_c:
            continue
        w = (1.0 - (r / tukey_c) ** 2) ** 2
        J[0], J[1], J[2] = py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx
        J[3], J[4], J[5] = nx, ny, nz
        for u in range(6):
            wu = w * J[u]
            b[u] += wu * r
            for v in range(u, 6):
                A[u, v] += wu * J[v]
    for u in range(6):
        for v in range(u):
            A[u, v] = A[v, u]
    return A, b
