"""Point normals: PCA of the k nearest points, oriented toward each point's sensor origin (NKSR's sensor trick).

With a cell size, the normal is estimated once per occupied cube of that edge, at the centroid of its points
(from the k nearest points of the whole input), and shared by the cube's points; each point still takes
the sign that faces its own sensor origin. The solver averages normals per level-0 voxel, so cubes smaller
than the voxel keep several independent normals per voxel at a fraction of one query per point.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.points.knn import KdTree
from nuplan_occ.points.plane_normals import pca_normals
from nuplan_occ.points.voxel_reduce import KeyIndex, group_means, voxel_keys


def estimate_normals(points: np.ndarray, sensor_origins: np.ndarray, knn: int = 30, cell_m: float = 0.0,
                     which: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (W, 3) of the points `which` (W,) indices (None: all N) of `points` (N, 3), all of which
    serve as neighbours; sensor_origins (W, 3) theirs, in the points' frame (metres).

    knn: neighbours of each PCA (fewer than 3 points give (0, 0, 1)); cell_m: estimate one normal per cube of
    this edge (m) and give it to the cube's points (module doc; a cube's centroid is that of all its points);
    0 = one estimate per point. Each normal is flipped so that dot(n, origin - point) >= 0, i.e. it points to
    the side the point was seen from.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    chosen = np.arange(len(pts)) if which is None else np.asarray(which, dtype=np.int64)
    if cell_m > 0:
        cells = KeyIndex(voxel_keys(pts, cell_m))
        wanted = np.zeros(len(cells.keys), dtype=bool)
        wanted[cells.ids[chosen]] = True
        queries = group_means(cells.ids, pts, len(cells.keys))[wanted]
        owner = (np.cumsum(wanted) - 1)[cells.ids[chosen]]
    else:
        queries, owner = pts[chosen], np.arange(len(chosen))
    _, neighbours = KdTree(pts).query(queries, k=int(knn))
    normals = pca_normals(pts, neighbours.reshape(len(queries), -1).astype(np.int64))[owner]
    view = np.asarray(sensor_origins, dtype=np.float64) - pts[chosen]
    flip = np.einsum("ij,ij->i", normals, view) < 0
    normals[flip] *= -1.0
    return normals
