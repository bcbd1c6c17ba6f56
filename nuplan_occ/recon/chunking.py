"""Scene-scale NKSR-lite: independent solves on xy chunks with overlap.

The level-0 lattice is anchored once for the whole input (a multiple of the coarsest voxel), so
every chunk uses the same lattice. A chunk owns the cells whose xy index lies in its core
[lo, hi) and solves with the points of the core grown by `chunk_overlap` metres on each side;
the meshes of the cores are concatenated (neighbouring cores meet on shared lattice planes, where
independently solved fields differ only by the solver's small residual). A core whose points (overlap
included) exceed `chunk_max_points` is halved across its longer side until each part fits, so a solve's
memory is bounded by the budget, not by how densely a long scene covers a tile.
Normals are estimated chunk by chunk too, each chunk's points (core and overlap) from the points within
NORMAL_HALO_M more, just before its solve: no step holds a scene-wide kNN structure or normal array (a point
of an overlap gets a normal in each chunk holding it).
Points, normals and the returned vertices are metres in the caller's frame.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from nuplan_occ.recon.extract import extract_mesh
from nuplan_occ.recon.nksr_lite import SolveStats, fit_field
from nuplan_occ.recon.normals import estimate_normals
from nuplan_occ.recon.params import ReconParams

CHUNK_SLACK = 1.05
"""Chunks may exceed chunk_size by this factor, so a 100.2 m tile splits into 2 x 2, not 3 x 3."""
NORMAL_HALO_M = 1.0
"""Neighbour points beyond a core's border taken into its normal estimates (m), so that normals near the
border match the ones a scene-wide estimate would give."""


def lattice_anchor(points: np.ndarray, params: ReconParams) -> np.ndarray:
    """(3,) metres: the lower corner of the level-0 lattice, a multiple of the coarsest voxel."""
    coarse = params.voxel_size * (1 << (params.levels - 1))
    return np.floor(points.min(axis=0) / coarse) * coarse


def chunk_bounds(cells_max: np.ndarray, params: ReconParams) -> list[np.ndarray]:
    """Per xy axis, the ascending cell bounds (level-0 voxels) of equal parts tiling [0, cells_max)
    (2,), each no larger than CHUNK_SLACK * chunk_size (one part when chunk_size <= 0)."""
    if params.chunk_size <= 0:
        return [np.array([0, int(extent)], dtype=np.int64) for extent in cells_max]
    target = params.chunk_size / params.voxel_size
    return [np.linspace(0, int(extent), max(1, int(np.ceil(extent / (CHUNK_SLACK * target)))) + 1)
            .round().astype(np.int64) for extent in cells_max]


TILE_CELLS = 16
"""Side (level-0 cells) of the square tiles by which ChunkTiles sorts the points: a grown core's points are
gathered tile by tile, and only the points of tiles on its border are tested one by one."""


@dataclass
class ChunkTiles:
    """The points (N, 3) of one reconstruction sorted by the TILE_CELLS tile holding their xy cell, and the
    chunk cores tiling them.

    anchor (3,) m: the lattice corner; bounds: per xy axis the core bounds in level-0 cells; order: point
    indices sorted by tile (row-major over (x, y) tile index, ascending within a tile); starts: where each
    tile's points begin in `order` (one more entry than tiles); tile_columns: tiles along y."""

    points: np.ndarray
    anchor: np.ndarray
    voxel_size: float
    bounds: list[np.ndarray]
    order: np.ndarray
    starts: np.ndarray
    tile_columns: int

    @classmethod
    def of(cls, points: np.ndarray, params: ReconParams) -> "ChunkTiles":
        anchor = lattice_anchor(points, params)
        cells = np.floor((points[:, :2] - anchor[:2]) / params.voxel_size).astype(np.int64)
        bounds = chunk_bounds(cells.max(axis=0) + 1, params)
        cells //= TILE_CELLS
        rows, columns = (int(n) for n in cells.max(axis=0) + 1)
        tile = cells[:, 0] * columns + cells[:, 1]
        del cells
        order = np.argsort(tile, kind="stable").astype(np.int32 if len(points) < 2**31 else np.int64)
        starts = np.searchsorted(tile[order], np.arange(rows * columns + 1))
        return cls(points, anchor, params.voxel_size, bounds, order, starts, columns)

    def cores(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every core's xy cell range [lo, hi) (level-0 voxels), row-major."""
        bx, by = self.bounds
        return [(np.array([bx[i], by[j]]), np.array([bx[i + 1], by[j + 1]]))
                for i in range(len(bx) - 1) for j in range(len(by) - 1)]

    def near(self, lo: np.ndarray, hi: np.ndarray, reach: float) -> np.ndarray:
        """Ascending indices of the points whose xy (level-0 units) lies in [lo - reach, hi + reach)."""
        rows = (len(self.starts) - 1) // self.tile_columns
        low, high = np.asarray(lo) - reach, np.asarray(hi) + reach
        first = np.clip(np.floor(low / TILE_CELLS).astype(int), 0, [rows, self.tile_columns])
        last = np.clip(np.ceil(high / TILE_CELLS).astype(int), first, [rows, self.tile_columns])
        inner_first = np.clip(np.ceil(low / TILE_CELLS).astype(int), first, last)  # tiles wholly inside
        inner_last = np.clip(np.floor(high / TILE_CELLS).astype(int), inner_first, last)
        inside, border = [], []

        def take(to: list, row: int, begin: int, end: int) -> None:
            if end > begin:
                to.append(self.order[self.starts[row * self.tile_columns + begin]:self.starts[row * self.tile_columns + end]])

        for row in range(first[0], last[0]):
            if inner_first[0] <= row < inner_last[0]:
                take(border, row, first[1], inner_first[1])
                take(inside, row, inner_first[1], inner_last[1])
                take(border, row, inner_last[1], last[1])
            else:
                take(border, row, first[1], last[1])
        edge = np.concatenate(border or [np.zeros(0, self.order.dtype)])
        return np.sort(np.concatenate([*inside, edge[self.within(edge, lo, hi, reach)]]))

    def within(self, indices: np.ndarray, lo: np.ndarray, hi: np.ndarray, reach: float) -> np.ndarray:
        """bool per index: whether that point's xy (level-0 units) lies in [lo - reach, hi + reach)."""
        u = (self.points[indices, :2] - self.anchor[:2]) / self.voxel_size
        return np.all((u >= lo - reach) & (u < hi + reach), axis=1)


def chunk_normals(tiles: ChunkTiles, near: np.ndarray, lo: np.ndarray, hi: np.ndarray, reach: float,
                  origins_at: Callable[[np.ndarray], np.ndarray], knn: int, cell_m: float = 0.0) -> np.ndarray:
    """(len(near), 3) float32 unit normals, facing their sensor origins, of the points `near` (tiles.near(lo,
    hi, reach): the points within `reach` level-0 voxels of the core [lo, hi)), estimated from those points and
    the ones within NORMAL_HALO_M beyond them (origins_at(indices): (k, 3) origins of the points at those
    indices; knn, cell_m: see `estimate_normals`). float32: the solver averages them per voxel."""
    context = tiles.near(lo, hi, reach + NORMAL_HALO_M / tiles.voxel_size)
    return estimate_normals(tiles.points[context], origins_at(near), knn, cell_m,
                            which=np.searchsorted(context, near)).astype(np.float32)


def budgeted_cores(tiles: ChunkTiles, reach: float, max_points: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every core (lo, hi) in level-0 cells with its points `tiles.near(lo, hi, reach)`, a tile's core halved
    across its longer side (recursively) while it holds more than `max_points` points and both halves
    stay wider than 2 * reach (max_points <= 0: no budget)."""
    pending = list(reversed(tiles.cores()))
    while pending:
        lo, hi = pending.pop()
        near = tiles.near(lo, hi, reach)
        axis = int(np.argmax(hi - lo))
        half = int(hi[axis] - lo[axis]) // 2
        if max_points <= 0 or len(near) <= max_points or half <= 2 * reach:
            yield lo, hi, near
            continue
        middle = lo[axis] + half
        first_hi, second_lo = hi.copy(), lo.copy()
        first_hi[axis], second_lo[axis] = middle, middle
        pending += [(second_lo, hi), (lo, first_hi)]


def nksr_mesh(points: np.ndarray, origins_at: Callable[[np.ndarray], np.ndarray],
              params: ReconParams) -> tuple[np.ndarray, np.ndarray, list[SolveStats]]:
    """NKSR-lite mesh (vertices (V, 3) float64 metres, faces (F, 3) int64) and per-chunk stats of
    points (N, 3) seen from their sensor origins (origins_at(indices) -> (k, 3)), metres in one frame."""
    tiles = ChunkTiles.of(points, params)
    h = params.voxel_size
    margin = params.chunk_overlap / h
    mask = params.mask_distance / h
    vertices, faces, stats = [], [], []
    n_vertices = 0
    for lo, hi, near in budgeted_cores(tiles, margin, params.chunk_max_points):
        if not tiles.within(near, lo, hi, min(mask, margin)).any():
            continue
        chunk = points[near]
        normals = chunk_normals(tiles, near, lo, hi, margin, origins_at, params.normal_knn, params.normal_cell_m)
        field, chunk_stats = fit_field(chunk, normals, tiles.anchor, params)
        verts, tris = extract_mesh(field, cKDTree((chunk - tiles.anchor) / h), mask, (lo, hi))
        stats.append(chunk_stats)
        vertices.append(tiles.anchor + verts * h)
        faces.append(tris + n_vertices)
        n_vertices += len(verts)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), stats
    return np.concatenate(vertices), np.concatenate(faces), stats
