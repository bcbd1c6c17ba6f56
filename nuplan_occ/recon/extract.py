"""Mesh extraction from an `ImplicitField`: marching cubes on the level-0 lattice, restricted to
a band around the data and to a distance-to-points mask.

All coordinates here are level-0 voxel units relative to the field's anchor; the corner (i, j, k)
of the lattice is at u = (i, j, k).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from nuplan_occ.recon.cleanup import compact
from nuplan_occ.recon.hierarchy import dilate
from nuplan_occ.recon.nksr_lite import ImplicitField

CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.int64)
BAND_DILATION = 2
"""Cells searched for the surface: occupied level-0 voxels grown by this many voxels."""


def masked_cells(
    field: ImplicitField, tree: cKDTree, mask_distance: float, xy_range: tuple[np.ndarray, np.ndarray] | None
) -> torch.Tensor:
    """Level-0 cells (C, 3) int64 in the band whose centre lies within `mask_distance` + half a
    cell diagonal (voxel units) of an input point (`tree` over the points in voxel units), optionally only cells whose
    xy index lies in [xy_range[0], xy_range[1])."""
    cells = dilate(field.hierarchy.levels[0].coords, BAND_DILATION)
    if xy_range is not None:
        lo, hi = (torch.from_numpy(np.asarray(v, dtype=np.int64)) for v in xy_range)
        cells = cells[((cells[:, :2] >= lo) & (cells[:, :2] < hi)).all(dim=1)]
    reach = mask_distance + 0.5 * np.sqrt(3.0)
    distance, _ = tree.query(cells.numpy() + 0.5, k=1, distance_upper_bound=reach)
    return cells[torch.from_numpy(distance < reach)]


def extract_mesh(
    field: ImplicitField, tree: cKDTree, mask_distance: float, xy_range: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of `field` inside the masked band (see `masked_cells`), keeping only the
    triangles whose vertices all lie within `mask_distance` (voxel units) of an input point.

    Returns (vertices (V, 3) float64 in level-0 voxel units, faces (F, 3) int64); faces are wound
    so that their normals point to f > 0 (the sensor side).
    """
    empty = (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    cells = masked_cells(field, tree, mask_distance, xy_range)
    if len(cells) == 0:
        return empty
    lo = cells.min(dim=0).values
    rel = (cells - lo).numpy()
    shape = tuple((rel.max(axis=0) + 2).tolist())
    needed = np.zeros(shape, dtype=bool)  # the cells' corners, marked in place of 8 rows per cell
    for i, j, k in CORNERS.tolist():
        needed[rel[:, 0] + i, rel[:, 1] + j, rel[:, 2] + k] = True
    corners = torch.from_numpy(np.argwhere(needed).astype(np.int64)) + lo  # lexicographic, as `needed` is C-ordered
    volume = np.ones(shape, dtype=np.float32)
    volume[needed] = field.evaluate(corners.to(torch.float64)).numpy()
    mask = np.zeros(shape, dtype=bool)
    upper = rel + 1  # skimage tests a cube's mask at its upper corner
    mask[upper[:, 0], upper[:, 1], upper[:, 2]] = True
    if min(shape) < 2:
        return empty
    try:
        verts, faces, _, _ = marching_cubes(volume, 0.0, mask=mask, gradient_direction="descent")
    except RuntimeError:  # no zero crossing inside the mask
        return empty
    verts = verts.astype(np.float64) + lo.numpy()
    distance, _ = tree.query(verts, k=1, distance_upper_bound=mask_distance)
    return compact(verts, faces.astype(np.int64), distance < mask_distance)
