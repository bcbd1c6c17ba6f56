"""Exact surface voxelization of triangle meshes and points, solid filling, and box masks.

All input coordinates are metres in the EGO frame of the grid (see nuplan_occ/grid.py). Internally
coordinates are converted to "voxel units" u = (p - grid.lower) / voxel_size, so voxel (i, j, k) is
the half-open unit cube [i, i+1) x [j, j+1) x [k, k+1).

Triangle rule (surface-exact): a voxel is occupied iff the closed triangle intersects the voxel's
half-open cube, realised as the closed cube [i-EPS, i+1-EPS]^3 (see nuplan_occ.voxel.triangle_sat: the
separating-axis test on every voxel of each triangle's bounding box, a numba kernel), so a surface lying
on a voxel boundary occupies only the voxel above it (the convention of `GridSpec.point_to_index`) and
large triangles never leave holes.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.voxel.triangle_sat import EPS, mark_triangle_voxels

TILE_EDGE = 256
"""Edge (voxels) of the dense boxes an unclipped lattice range is voxelized in (16 M bools at most)."""


class VoxelizeError(ValueError):
    """Malformed mesh or point input to the voxelizer."""


def _as_vertices(vertices: np.ndarray, name: str) -> np.ndarray:
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise VoxelizeError(f"{name}: expected (V, 3) vertices, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise VoxelizeError(f"{name}: vertices contain NaN or inf")
    return v


def _as_faces(faces: np.ndarray, n_vertices: int, name: str) -> np.ndarray:
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise VoxelizeError(f"{name}: expected (F, 3) integer faces, got shape {f.shape} dtype {f.dtype}")
    if f.min() < 0 or f.max() >= n_vertices:
        raise VoxelizeError(f"{name}: face index out of range [0, {n_vertices})")
    return f.astype(np.int64)


def to_voxel_units(points_ego: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(N, 3) ego-frame metres -> (N, 3) float64 voxel units relative to the grid's lower corner."""
    return (np.asarray(points_ego, dtype=np.float64).reshape(-1, 3) - grid.lower) / grid.voxel_size


def unique_indices(indices: np.ndarray) -> np.ndarray:
    """Unique rows of an (M, 3) int64 index array (any integers, also outside the grid), sorted."""
    idx = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    if len(idx) == 0:
        return idx
    lo = idx.min(axis=0)
    dims = idx.max(axis=0) - lo + 1
    key = ((idx[:, 0] - lo[0]) * dims[1] + (idx[:, 1] - lo[1])) * dims[2] + (idx[:, 2] - lo[2])
    if np.prod(dims) <= 8 * len(idx) + 1_000_000:  # dense scatter beats sorting
        seen = np.zeros(int(np.prod(dims)), dtype=bool)
        seen[key] = True
        key = np.flatnonzero(seen)
    else:
        key = np.unique(key)
    return np.stack(np.unravel_index(key, tuple(dims)), axis=1) + lo


def triangle_voxel_grid(tri_units: np.ndarray, lo: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """Bool array of `shape`: element v - lo is set for every voxel v of the box [lo, lo + shape) touched by
    a triangle of tri_units (T, 3, 3), voxel units (triangles outside the box are ignored)."""
    vertices = np.ascontiguousarray(tri_units, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(shape, dtype=bool)
    mark_triangle_voxels(vertices, np.arange(len(vertices), dtype=np.int64).reshape(-1, 3), np.zeros(3), 1.0,
                         np.asarray(lo, dtype=np.int64), out)
    return out


def triangle_voxel_indices(tri_units: np.ndarray) -> np.ndarray:
    """Unique sorted (M, 3) int64 voxel indices touched by triangles (T, 3, 3) given in voxel units
    (unbounded: the triangles' lattice range is covered in boxes of at most TILE_EDGE^3 voxels)."""
    tri = np.ascontiguousarray(tri_units, dtype=np.float64).reshape(-1, 3, 3)
    if len(tri) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    first = np.floor(np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2]) + EPS).astype(np.int64)  # (T, 3)
    last = np.floor(np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2]) + EPS).astype(np.int64)  # lattice box
    lo, hi = first.min(axis=0), last.max(axis=0) + 1
    found = []
    for corner in itertools.product(*[range(int(a), int(b), TILE_EDGE) for a, b in zip(lo, hi)]):
        start = np.asarray(corner, dtype=np.int64)
        stop = np.minimum(start + TILE_EDGE, hi)
        meets = np.all((first < stop) & (last >= start), axis=1)
        touched = np.nonzero(triangle_voxel_grid(tri[meets], start, tuple(stop - start)))
        found.append(np.stack(touched, axis=1) + start)
    return found[0] if len(found) == 1 else unique_indices(np.concatenate(found))


def mesh_voxel_grid(vertices: np.ndarray, faces: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """Dense bool (X, Y, Z) grid of the voxels a mesh surface touches (exact triangle/voxel overlap);
    vertices (V, 3) metres in the ego frame, faces (F, 3) int (empty: the vertices are points)."""
    v = _as_vertices(vertices, "mesh_voxel_grid")
    f = _as_faces(faces, len(v), "mesh_voxel_grid")
    if len(f) == 0:
        return indices_to_grid(np.floor(to_voxel_units(v, grid)).astype(np.int64), grid)
    out = np.zeros(grid.shape, dtype=bool)
    mark_triangle_voxels(np.ascontiguousarray(v), np.ascontiguousarray(f), np.asarray(grid.lower, dtype=np.float64),
                         float(grid.voxel_size), np.zeros(3, dtype=np.int64), out)
    return out


def mesh_voxel_indices(vertices: np.ndarray, faces: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                       clip: bool = True) -> np.ndarray:
    """Unique (M, 3) int64 indices of the voxels a mesh surface touches (exact triangle/voxel overlap).

    vertices (V, 3) metres in the ego frame; faces (F, 3) int. With no faces, the vertices are treated
    as points. clip=True drops indices outside the grid; clip=False keeps them (indices on the grid's
    lattice extended beyond its bounds, used to fill objects that stick out of the grid).
    """
    if clip:
        return np.stack(np.nonzero(mesh_voxel_grid(vertices, faces, grid)), axis=1)
    v = _as_vertices(vertices, "mesh_voxel_indices")
    f = _as_faces(faces, len(v), "mesh_voxel_indices")
    if len(f) == 0:
        return unique_indices(np.floor(to_voxel_units(v, grid)).astype(np.int64))
    return triangle_voxel_indices(to_voxel_units(v, grid)[f])


def inside_grid(indices: np.ndarray, grid: GridSpec) -> np.ndarray:
    """The rows of an (M, 3) index array that lie inside the grid."""
    shape = np.asarray(grid.shape)
    return indices[np.all((indices >= 0) & (indices < shape), axis=1)]


def indices_to_grid(indices: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """Dense bool (X, Y, Z) grid with the given (M, 3) indices set (indices outside the grid ignored)."""
    out = np.zeros(grid.shape, dtype=bool)
    idx = inside_grid(np.asarray(indices, dtype=np.int64).reshape(-1, 3), grid)
    out[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return out


def fill_enclosed(indices: np.ndarray) -> np.ndarray:
    """Add to a closed voxel surface the voxels it encloses (not 6-connected to the outside).

    indices (M, 3) int64 on any lattice range (may extend beyond the grid). An exact (conservative)
    voxelization of a watertight mesh separates inside from outside, so its interior is filled; a
    surface with a gap encloses nothing and is returned unchanged.
    """
    if len(indices) == 0:
        return indices
    lo = indices.min(axis=0) - 1
    dims = indices.max(axis=0) - lo + 2
    local = np.zeros(tuple(dims), dtype=bool)
    rel = indices - lo
    local[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    return np.argwhere(ndimage.binary_fill_holes(local)) + lo


def voxelize_mesh(vertices: np.ndarray, faces: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                  fill_solid: bool = False) -> np.ndarray:
    """Bool (X, Y, Z) grid of the voxels a triangle surface touches (exact overlap, see module doc).

    vertices (V, 3) metres in the ego frame; faces (F, 3) int (empty: vertices voxelized as points).
    fill_solid: also fill the voxels enclosed by the surface (for watertight object meshes); the fill
    is done on the unclipped lattice so objects cut by the grid border are still filled.
    """
    if not fill_solid:
        return mesh_voxel_grid(vertices, faces, grid)
    return indices_to_grid(fill_enclosed(mesh_voxel_indices(vertices, faces, grid, clip=False)), grid)


def voxelize_points(points: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """Bool (X, Y, Z) grid of the voxels containing points (N, 3), metres in the ego frame."""
    idx, inside = grid.point_to_index(_as_vertices(points, "voxelize_points"))
    return indices_to_grid(idx[inside], grid)


def in_box(points_ego: np.ndarray, center: np.ndarray, yaw: float, size: np.ndarray,
           margin_m: float = 0.0) -> np.ndarray:
    """(N,) bool: ego-frame points inside an upright box (centre, yaw, [length, width, height]) grown
    by margin_m on every side (boundary included)."""
    rel = np.asarray(points_ego, dtype=np.float64).reshape(-1, 3) - np.asarray(center, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)
    return np.all(np.abs(local) <= np.asarray(size, dtype=np.float64) / 2.0 + margin_m, axis=1)


def box_voxel_indices(center: np.ndarray, yaw: float, size: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                      margin_m: float = 0.0) -> np.ndarray:
    """(M, 3) indices of grid voxels whose centre lies inside the box (ego frame) grown by margin_m."""
    half = np.asarray(size, dtype=np.float64) / 2.0 + margin_m
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    reach = np.array([c * half[0] + s * half[1], s * half[0] + c * half[1], half[2]])
    lo = np.floor(to_voxel_units(np.asarray(center) - reach, grid)[0]).astype(np.int64)
    hi = np.floor(to_voxel_units(np.asarray(center) + reach, grid)[0]).astype(np.int64)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, np.asarray(grid.shape) - 1)
    if np.any(hi < lo):
        return np.zeros((0, 3), dtype=np.int64)
    axes = [np.arange(a, b + 1) for a, b in zip(lo, hi)]
    cand = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return cand[in_box(grid.index_to_center(cand), center, yaw, size, margin_m)]


def fill_box_interior(occupied: np.ndarray, center: np.ndarray, yaw: float, size: np.ndarray,
                      grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """Copy of a bool grid with every voxel whose centre is inside the box (ego frame) set: the crude
    solid for objects given as raw points (no closed surface to fill)."""
    out = np.array(occupied, dtype=bool, copy=True)
    idx = box_voxel_indices(center, yaw, size, grid)
    out[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return out
