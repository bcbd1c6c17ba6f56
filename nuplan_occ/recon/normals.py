"""Point normals: PCA of the k nearest points, oriented toward each point's sensor origin (NKSR's sensor trick).

With a cell size, the normal is estimated once per occupied cube of that edge, at the centroid of its points
(from the k nearest points of the whole input), and shared by the cube's points; each point still takes
the sign that faces its own sensor origin. The solver averages normals per level-0 voxel, so cubes smaller
than the voxel keep several independent normals per voxel at a fraction of one query per point.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.fbsa.knn import KdTree
from nuplan_occ.fbsa.plane_normals import pca_normals
from nuplan_occ.fbsa.voxel_reduce import KeyIndex, group_means, voxel_keys


def estimate_normals(points: np.ndarray, sensor_origins: np.ndarray, knn: int = 30, cell_m: float = 0.0) -> np.ndarray:
    """Unit normals (N, 3) of `points` (N, 3), both arrays in the same frame (metres).

    knn: neighbours of each PCA (fewer than 3 points give (0, 0, 1)); cell_m: estimate one normal per cube of
    this edge (m) and give it to the cube's points (module doc); 0 = one estimate per point. Each normal is
    flipped so that dot(n, origin - point) >= 0, i.e. it points to the side the point was seen from.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if cell_m > 0:
        cells = KeyIndex(voxel_keys(pts, cell_m))
        queries, owner = group_means(cells.ids, pts, len(cells.keys)), cells.ids
    else:
        queries, owner = pts, np.arange(len(pts))
    _, neighbours = KdTree(pts).query(queries, k=int(knn))
    normals = pca_normals(pts, neighbours.reshape(len(queries), -1).astype(np.int64))[owner]
    view = np.asarray(sensor_origins, dtype=np.float64) - pts
    flip = np.einsum("ij,ij->i", normals, view) < 0
    normals[flip] *= -1.0
    return normals
