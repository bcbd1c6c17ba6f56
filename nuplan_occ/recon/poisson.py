"""Baseline: Open3D screened Poisson with density and distance trimming.

Poisson is watertight and closes open outdoor scenes with a bubble, so low-density vertices
(below the `density_quantile` of Poisson's per-vertex densities) and vertices farther than
`mask_distance` from every input point are removed. Points and normals are metres in one frame.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from nuplan_occ.recon.cleanup import compact


def poisson_mesh(
    points: np.ndarray, normals: np.ndarray, depth: int, density_quantile: float, mask_distance: float, tree: cKDTree, threads: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """Trimmed Poisson mesh (vertices (V, 3) float64 metres, faces (F, 3) int64); `tree` is a
    KD-tree over `points` for the distance trim; threads -1 = all cores."""
    import open3d as o3d  # heavy import (~1 s), only for this non-default method

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    cloud.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=int(depth), n_threads=int(threads))
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.triangles).astype(np.int64)
    densities = np.asarray(densities)
    keep = densities >= np.quantile(densities, density_quantile) if len(densities) else densities.astype(bool)
    distance, _ = tree.query(vertices, k=1, distance_upper_bound=mask_distance)
    keep &= distance < mask_distance
    return compact(vertices, faces, keep)

