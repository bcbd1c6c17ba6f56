"""Mesh clean-up with pymeshlab after reconstruction.

- Small floating components (fewer than `min_faces` faces) are removed: on real scans they are
  isolated returns (birds, dust, single stray voxels) that the implicit field turns into blobs.
- Holes bounded by at most `max_hole_edges` edges are closed (off by default): marching cubes on
  a trimmed field leaves genuine open borders (the edge of the observed ground), and pymeshlab
  treats every short border loop as a hole, so closing only helps for small gaps inside surfaces.
  Non-manifold edges are repaired first because pymeshlab's hole filler requires a 2-manifold.
Vertices stay in the caller's frame and units.
"""

from __future__ import annotations

import numpy as np
import pymeshlab


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, min_faces: int, max_hole_edges: int) -> tuple[np.ndarray, np.ndarray]:
    """Cleaned (vertices (V', 3) float64, faces (F', 3) int64) of a triangle mesh."""
    if len(faces) == 0 or (min_faces <= 1 and max_hole_edges <= 0):
        return vertices, faces
    meshes = pymeshlab.MeshSet()
    meshes.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, dtype=np.float64), face_matrix=np.asarray(faces, dtype=np.int32)))
    meshes.meshing_remove_duplicate_vertices()
    if min_faces > 1:
        meshes.meshing_remove_connected_component_by_face_number(mincomponentsize=int(min_faces), removeunref=True)
    if max_hole_edges > 0 and meshes.current_mesh().face_number() > 0:
        meshes.meshing_repair_non_manifold_edges()
        meshes.meshing_close_holes(maxholesize=int(max_hole_edges), selfintersection=False)
    mesh = meshes.current_mesh()
    return mesh.vertex_matrix().astype(np.float64), mesh.face_matrix().astype(np.int64)


def compact(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces whose three vertices are kept, with vertices renumbered."""
    faces = faces[keep[faces].all(axis=1)]
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces]
