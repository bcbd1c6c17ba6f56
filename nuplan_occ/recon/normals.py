"""Point normals: Open3D kNN PCA, oriented toward each point's sensor origin (NKSR's sensor trick)."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def estimate_normals(points: np.ndarray, sensor_origins: np.ndarray, knn: int = 30) -> np.ndarray:
    """Unit normals (N, 3) of `points` (N, 3), both arrays in the same frame (metres).

    Each normal is flipped so that dot(n, origin - point) >= 0, i.e. it points to the side the
    point was seen from.
    """
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=int(knn)))
    normals = np.asarray(pcd.normals)
    view = np.asarray(sensor_origins, dtype=np.float64) - points
    flip = np.einsum("ij,ij->i", normals, view) < 0
    normals[flip] *= -1.0
    return normals
