"""The paper's (UniScenev2 / Nuplan-Occ) voxelization and BEV labeling, re-implemented from its description
to compare against ours on the same input. Pure numpy.

- paper_voxelize_vertices: only mesh VERTICES are voxelized, after one midpoint subdivision of the
  mesh; each voxel takes the majority label of its vertices. Triangles larger than a voxel leave holes.
- paper_column_stamp: every background (OTHER) voxel of a drivable BEV column becomes ROAD and of a
  line column ROAD_LINE, whatever its height (a tree over the road becomes road).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import OTHER, ROAD, ROAD_LINE


def midpoint_subdivide(vertices: np.ndarray, faces: np.ndarray,
                       labels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices after one midpoint subdivision: the originals plus each unique edge's midpoint (a
    midpoint takes the label of its edge's first vertex). Returns (vertices, labels)."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges = np.unique(edges, axis=0)
    mids = (vertices[edges[:, 0]] + vertices[edges[:, 1]]) / 2.0
    out_labels = None if labels is None else np.concatenate([labels, labels[edges[:, 0]]])
    return np.concatenate([vertices, mids]), out_labels


def paper_voxelize_vertices(vertices_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID, faces: np.ndarray | None = None,
                            labels: np.ndarray | None = None) -> np.ndarray:
    """uint8 (X, Y, Z) semantics from mesh vertices (V, 3) metres in the ego frame: one midpoint
    subdivision if faces are given, floor to voxels, majority label per voxel (labels (V,) uint8,
    default all OTHER; ties go to the smaller id)."""
    v = np.asarray(vertices_ego, dtype=np.float64).reshape(-1, 3)
    lab = np.full(len(v), OTHER, dtype=np.uint8) if labels is None else np.asarray(labels, dtype=np.uint8)
    if faces is not None and len(faces):
        v, lab = midpoint_subdivide(v, faces, lab)
    idx, inside = grid.point_to_index(v)
    idx, lab = idx[inside], lab[inside]
    out = np.zeros(grid.shape, dtype=np.uint8)
    if len(idx) == 0:
        return out
    flat = np.ravel_multi_index(idx.T, grid.shape)
    pairs, counts = np.unique(np.stack([flat, lab.astype(np.int64)], axis=1), axis=0, return_counts=True)
    order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))  # per voxel: most votes, then smaller id
    pairs = pairs[order]
    first = np.concatenate([[True], pairs[1:, 0] != pairs[:-1, 0]])
    out.reshape(-1)[pairs[first, 0]] = pairs[first, 1]
    return out


def paper_column_stamp(semantics: np.ndarray, bev_drivable: np.ndarray, bev_line: np.ndarray,
                       grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """Copy of semantics (X, Y, Z) where every OTHER voxel in a drivable column (bool (X, Y)) is ROAD
    and in a line column (bool (X, Y)) ROAD_LINE (line wins), at any height."""
    if tuple(semantics.shape) != tuple(grid.shape):
        raise ValueError(f"paper_column_stamp: semantics shape {semantics.shape} != grid {grid.shape}")
    out = semantics.copy()
    background = out == OTHER
    out[background & np.asarray(bev_drivable, dtype=bool)[:, :, None]] = ROAD
    out[background & np.asarray(bev_line, dtype=bool)[:, :, None]] = ROAD_LINE
    return out
