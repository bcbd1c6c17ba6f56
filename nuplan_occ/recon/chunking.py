"""Scene-scale NKSR-lite: independent solves on xy chunks with overlap (reference A.9, A.11.5).

The level-0 lattice is anchored once for the whole input (a multiple of the coarsest voxel), so
every chunk uses the same lattice. A chunk owns the cells whose xy index lies in its core
[lo, hi) and solves with the points of the core grown by `chunk_overlap` metres on each side;
the meshes of the cores are concatenated (neighbouring cores meet on shared lattice planes, where
independently solved fields differ only by the solver's small residual).
Points, normals and the returned vertices are metres in the caller's frame.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from nuplan_occ.recon.extract import extract_mesh
from nuplan_occ.recon.nksr_lite import SolveStats, fit_field
from nuplan_occ.recon.params import ReconParams

CHUNK_SLACK = 1.05
"""Chunks may exceed chunk_size by this factor, so a 100.2 m tile splits into 2 x 2, not 3 x 3."""


def lattice_anchor(points: np.ndarray, params: ReconParams) -> np.ndarray:
    """(3,) metres: the lower corner of the level-0 lattice, a multiple of the coarsest voxel."""
    coarse = params.voxel_size * (1 << (params.levels - 1))
    return np.floor(points.min(axis=0) / coarse) * coarse


def chunk_ranges(cells_max: np.ndarray, params: ReconParams) -> list[tuple[np.ndarray, np.ndarray]]:
    """Core xy cell ranges [lo, hi) (level-0 voxels) tiling [0, cells_max) (2,) in equal parts no
    larger than CHUNK_SLACK * chunk_size."""
    if params.chunk_size <= 0:
        return [(np.zeros(2, dtype=np.int64), cells_max.astype(np.int64))]
    target = params.chunk_size / params.voxel_size
    bounds = []
    for extent in cells_max:
        count = max(1, int(np.ceil(extent / (CHUNK_SLACK * target))))
        bounds.append(np.linspace(0, int(extent), count + 1).round().astype(np.int64))
    return [
        (np.array([bounds[0][i], bounds[1][j]]), np.array([bounds[0][i + 1], bounds[1][j + 1]]))
        for i in range(len(bounds[0]) - 1) for j in range(len(bounds[1]) - 1)
    ]


def nksr_mesh(points: np.ndarray, normals: np.ndarray, params: ReconParams) -> tuple[np.ndarray, np.ndarray, list[SolveStats]]:
    """NKSR-lite mesh (vertices (V, 3) float64 metres, faces (F, 3) int64) and per-chunk stats."""
    h = params.voxel_size
    anchor = lattice_anchor(points, params)
    u = (points - anchor) / h
    cells_max = np.floor(u[:, :2].max(axis=0)).astype(np.int64) + 1
    margin = params.chunk_overlap / h
    mask = params.mask_distance / h
    vertices, faces, stats = [], [], []
    n_vertices = 0
    for lo, hi in chunk_ranges(cells_max, params):
        near = np.all((u[:, :2] >= lo - margin) & (u[:, :2] < hi + margin), axis=1)
        core = np.all((u[:, :2] >= lo - mask) & (u[:, :2] < hi + mask), axis=1)
        if not core.any():
            continue
        field, chunk_stats = fit_field(points[near], normals[near], anchor, params)
        verts, tris = extract_mesh(field, cKDTree(u[near]), mask, (lo, hi))
        stats.append(chunk_stats)
        vertices.append(anchor + verts * h)
        faces.append(tris + n_vertices)
        n_vertices += len(verts)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), stats
    return np.concatenate(vertices), np.concatenate(faces), stats
