"""Exact surface voxelization of triangle meshes and points, solid filling, and box masks. Pure numpy.

All input coordinates are metres in the EGO frame of the grid (see nuplan_occ/grid.py). Internally
coordinates are converted to "voxel units" u = (p - grid.lower) / voxel_size, so voxel (i, j, k) is
the half-open unit cube [i, i+1) x [j, j+1) x [k, k+1).

Triangle rule (surface-exact): a voxel is occupied iff the closed triangle intersects the voxel's
half-open cube. The half-open cube is realised as the closed cube [i-EPS, i+1-EPS]^3 with EPS = 1e-7
voxel (a lattice shifted by EPS, no gaps between cubes), so a surface lying on a voxel boundary, or
within rounding error of it, occupies only the voxel above it (the convention of
`GridSpec.point_to_index`). The test is the separating-axis theorem (13 axes, Akenine-Moeller's
triangle/box overlap). Triangles with an edge longer than one voxel are first split into n^2 congruent
sub-triangles (exact: their union is the triangle), so every candidate set is at most 2x2x2 voxels and
large triangles never leave holes. Triangles are split and tested SPLIT_CHUNK at a time (the working set
stays in cache), on per-component arrays, dropping candidates as soon as a group of axes separates them.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from nuplan_occ.grid import DEFAULT_GRID, GridSpec

EPS = 1e-7
"""Shift (voxel units) of the closed test cubes [i-EPS, i+1-EPS] that emulates half-open voxels."""

SPLIT_CHUNK = 8_192
"""(Sub-)triangles voxelized at once (at most 8 candidate voxels each): bounds temporary memory and keeps
the working set in cache."""

DENSE_LIMIT = 64_000_000
"""Largest lattice box (voxels) over a mesh whose touched voxels are collected in a dense bitmap."""

_OFFSETS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)


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


def _subdivision_template(n: int) -> np.ndarray:
    """(n*n, 3, 2) barycentric (a, b) weights of the sub-triangles of a triangle split n times per edge:
    lattice points P(i, j) = (i/n, j/n); "up" triangles P(i,j) P(i+1,j) P(i,j+1) for i+j <= n-1 and
    "down" triangles P(i+1,j) P(i+1,j+1) P(i,j+1) for i+j <= n-2."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up_i, up_j = i[i + j <= n - 1], j[i + j <= n - 1]
    dn_i, dn_j = i[i + j <= n - 2], j[i + j <= n - 2]
    up = np.stack([np.stack([up_i, up_j], -1), np.stack([up_i + 1, up_j], -1), np.stack([up_i, up_j + 1], -1)], 1)
    dn = np.stack([np.stack([dn_i + 1, dn_j], -1), np.stack([dn_i + 1, dn_j + 1], -1),
                   np.stack([dn_i, dn_j + 1], -1)], 1)
    return np.concatenate([up, dn], axis=0).astype(np.float64) / n


def _split_long_triangles(tri: np.ndarray, max_edge: float = 0.999):
    """Yield, in chunks of about SPLIT_CHUNK, triangles whose edges are all <= max_edge (voxel units)
    and whose union is that of the (T, 3, 3) triangles `tri`."""
    edges = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], axis=1)
    longest = np.linalg.norm(edges, axis=2).max(axis=1)
    n_split = np.maximum(np.ceil(longest / max_edge), 1).astype(np.int64)
    short = tri[n_split == 1]
    for start in range(0, len(short), SPLIT_CHUNK):
        yield short[start:start + SPLIT_CHUNK]
    for n in np.unique(n_split[n_split > 1]):
        group = tri[n_split == n]
        weights = _subdivision_template(int(n))  # (n^2, 3, 2)
        per_chunk = max(1, SPLIT_CHUNK // len(weights))
        for start in range(0, len(group), per_chunk):
            g = group[start:start + per_chunk]
            e1, e2 = (g[:, 1] - g[:, 0])[:, None, None, :], (g[:, 2] - g[:, 0])[:, None, None, :]
            sub = g[:, None, None, 0, :] + weights[None, :, :, 0:1] * e1 + weights[None, :, :, 1:2] * e2
            yield sub.reshape(-1, 3, 3)


def _min3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a, b), c)


def _max3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a, b), c)


def _triangle_box_overlap(tri: np.ndarray, voxel: np.ndarray) -> np.ndarray:
    """(M,) bool: closed triangle intersects voxel cube [v-EPS, v+1-EPS]^3 (voxel units); tri (3, 3, M)
    [vertex, axis, candidate], voxel (3, M) int [axis, candidate].

    Separating-axis test: 3 cube normals, the triangle normal, and the 9 cross products of cube axes
    with triangle edges, on vertices u = vertex - cube centre. Works on per-component arrays;
    candidates failing a group of tests are dropped before the next group (the verdict is the AND of
    all tests, so the order does not matter)."""
    h = 0.5
    center = voxel.astype(np.float64) + (h - EPS)
    u = [[tri[i, a] - center[a] for a in range(3)] for i in range(3)]  # u[vertex][axis], (M,)
    ok = np.ones(voxel.shape[1], dtype=bool)
    for a in range(3):
        ok &= (_min3(u[0][a], u[1][a], u[2][a]) <= h) & (_max3(u[0][a], u[1][a], u[2][a]) >= -h)
    alive = np.flatnonzero(ok)
    u = [[c[alive] for c in vertex] for vertex in u]
    e0, e1 = [u[1][a] - u[0][a] for a in range(3)], [u[2][a] - u[0][a] for a in range(3)]
    normal = [e0[1] * e1[2] - e0[2] * e1[1], e0[2] * e1[0] - e0[0] * e1[2], e0[0] * e1[1] - e0[1] * e1[0]]
    dot = normal[0] * u[0][0] + normal[1] * u[0][1] + normal[2] * u[0][2]
    keep = np.abs(dot) <= h * (np.abs(normal[0]) + np.abs(normal[1]) + np.abs(normal[2]))
    for start, stop in ((0, 1), (1, 2), (2, 0)):
        idx = np.flatnonzero(keep)
        alive, u = alive[idx], [[c[idx] for c in vertex] for vertex in u]
        f = [u[stop][a] - u[start][a] for a in range(3)]
        keep = np.ones(len(alive), dtype=bool)
        for a, b in ((1, 2), (2, 0), (0, 1)):  # axis e_c x f has components -f_b at a, f_a at b
            p0 = u[0][b] * f[a] - u[0][a] * f[b]
            p1 = u[1][b] * f[a] - u[1][a] * f[b]
            p2 = u[2][b] * f[a] - u[2][a] * f[b]
            r = h * (np.abs(f[a]) + np.abs(f[b]))
            keep &= (_min3(p0, p1, p2) <= r) & (_max3(p0, p1, p2) >= -r)
    out = np.zeros(voxel.shape[1], dtype=bool)
    out[alive[keep]] = True
    return out


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


def _small_triangle_voxels(tri: np.ndarray) -> np.ndarray:
    """(M, 3) voxel indices (with repeats) touched by triangles (T, 3, 3), voxel units, whose edges are
    shorter than one voxel: each spans at most 2 x 2 x 2 candidate voxels, tested exactly."""
    base = np.floor(_min3(tri[:, 0], tri[:, 1], tri[:, 2]) + EPS).astype(np.int64)
    extent = np.floor(_max3(tri[:, 0], tri[:, 1], tri[:, 2]) + EPS).astype(np.int64) - base  # 0 or 1
    single = (extent[:, 0] == 0) & (extent[:, 1] == 0) & (extent[:, 2] == 0)
    multi = np.flatnonzero(~single)
    ext = extent[multi]
    valid = ((_OFFSETS[None, :, 0] <= ext[:, 0:1]) & (_OFFSETS[None, :, 1] <= ext[:, 1:2])
             & (_OFFSETS[None, :, 2] <= ext[:, 2:3]))  # (m, 8)
    t_idx, o_idx = np.nonzero(valid)
    t_idx = multi[t_idx]
    voxels = base[t_idx] + _OFFSETS[o_idx]
    components = np.ascontiguousarray(tri.transpose(1, 2, 0))  # (vertex, axis, triangle)
    hit = _triangle_box_overlap(np.take(components, t_idx, axis=2), np.ascontiguousarray(voxels.T))
    return np.concatenate([base[single], voxels[hit]], axis=0)


def triangle_voxel_indices(tri_units: np.ndarray) -> np.ndarray:
    """Unique (M, 3) int64 voxel indices touched by triangles (T, 3, 3) given in voxel units (unbounded)."""
    if len(tri_units) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    lo = np.floor(tri_units.reshape(-1, 3).min(axis=0) + EPS).astype(np.int64) - 1  # sub-triangles stay
    dims = np.floor(tri_units.reshape(-1, 3).max(axis=0) + EPS).astype(np.int64) + 2 - lo  # inside, +-1 spare
    if np.prod(dims.astype(np.float64)) > DENSE_LIMIT:
        found = [_small_triangle_voxels(tri) for tri in _split_long_triangles(tri_units)]
        return unique_indices(np.concatenate(found, axis=0))
    seen = np.zeros(int(np.prod(dims)), dtype=bool)
    for tri in _split_long_triangles(tri_units):
        rel = _small_triangle_voxels(tri) - lo
        seen[(rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]] = True
    return np.stack(np.unravel_index(np.flatnonzero(seen), tuple(dims)), axis=1) + lo


def _keep_near_grid(tri_units: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Triangles whose bounding box meets the grid box [0, shape] (voxel units)."""
    shape = np.asarray(grid.shape, dtype=np.float64)
    hi = _max3(tri_units[:, 0], tri_units[:, 1], tri_units[:, 2])
    lo = _min3(tri_units[:, 0], tri_units[:, 1], tri_units[:, 2])
    near = np.all((hi >= 0) & (lo <= shape), axis=1)
    return tri_units[near]


def mesh_voxel_indices(vertices: np.ndarray, faces: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                       clip: bool = True) -> np.ndarray:
    """Unique (M, 3) int64 indices of the voxels a mesh surface touches (exact triangle/voxel overlap).

    vertices (V, 3) metres in the ego frame; faces (F, 3) int. With no faces, the vertices are treated
    as points. clip=True drops indices outside the grid; clip=False keeps them (indices on the grid's
    lattice extended beyond its bounds, used to fill objects that stick out of the grid).
    """
    v = _as_vertices(vertices, "mesh_voxel_indices")
    f = _as_faces(faces, len(v), "mesh_voxel_indices")
    if len(f) == 0:
        idx = unique_indices(np.floor(to_voxel_units(v, grid)).astype(np.int64))
    else:
        tri = to_voxel_units(v, grid)[f]
        idx = triangle_voxel_indices(_keep_near_grid(tri, grid) if clip else tri)
    return inside_grid(idx, grid) if clip else idx


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
    idx = mesh_voxel_indices(vertices, faces, grid, clip=not fill_solid)
    if fill_solid:
        idx = fill_enclosed(idx)
    return indices_to_grid(idx, grid)


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
