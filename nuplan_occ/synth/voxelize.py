"""Exact overlap of geometric primitives with the voxels of a grid (pure numpy, no I/O).

All inputs are in the grid's frame (the ego frame for truth), metres. A voxel is the half-open box
[lo, hi) of `GridSpec`; a primitive is a closed set. A voxel is hit when the two intersect:
- along the three grid axes the test is exact for half-open voxels (candidate index ranges are
  floor((min - lo)/s) .. floor((max - lo)/s), so a surface lying exactly on the plane z = k*s belongs to
  the voxel above it, never to both);
- along the oblique separating axes (rotated edges, triangle normals, edge cross products) touching counts
  as overlap (a measure-zero tie).

Primitives:
- upright prisms: an oriented rectangle in x-y (centre, half extents along its own axes u, v, yaw) swept
  over z in [z0, z1]. A zero half extent gives a vertical face (a segment swept in z); z0 == z1 gives a
  horizontal rectangle. Solid boxes are prisms with both extents and a z range.
- triangles: arbitrary 3D triangles (Akenine-Moller separating-axis test, 13 axes).

Each function returns (flat voxel index, primitive index) pairs; `reduce_labels` turns labelled hits
into semantics / instance grids with a priority rule.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import GridSpec

_EPS = 1e-9


def _ragged_offsets(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For counts (N,) -> (owner (M,), local offset (M,)) enumerating 0..counts[n]-1 for every n."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    owner = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    return owner, np.arange(total, dtype=np.int64) - starts[owner]


def _index_range(lo_m: np.ndarray, hi_m: np.ndarray, axis_min: float, size: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive voxel index range [first, last] along one grid axis of closed intervals [lo_m, hi_m]
    against half-open voxels; ranges fully outside the grid come back with first > last."""
    first = np.floor((lo_m - axis_min) / size).astype(np.int64)
    last = np.floor((hi_m - axis_min) / size).astype(np.int64)
    outside = (last < 0) | (first > n - 1)
    first = np.clip(first, 0, n - 1)
    last = np.where(outside, first - 1, np.clip(last, 0, n - 1))
    return first, last


def prism_voxel_hits(center_xy: np.ndarray, half_uv: np.ndarray, yaw: np.ndarray, z0: np.ndarray, z1: np.ndarray,
                     grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Voxels hit by N upright prisms given in the grid frame.

    center_xy (N, 2) m, half_uv (N, 2) m (half length along the prism's heading u, half width along v),
    yaw (N,) rad, z0 <= z1 (N,) m. Returns (flat voxel index (M,), prism index (M,)); flat index is
    (i * ny + j) * nz + k.
    """
    center_xy = np.asarray(center_xy, np.float64).reshape(-1, 2)
    half_uv = np.asarray(half_uv, np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, np.float64).reshape(-1)
    z0 = np.asarray(z0, np.float64).reshape(-1)
    z1 = np.asarray(z1, np.float64).reshape(-1)
    nx, ny, nz = grid.shape
    s, h = grid.voxel_size, grid.voxel_size / 2.0
    c, sn = np.cos(yaw), np.sin(yaw)
    ex = half_uv[:, 0] * np.abs(c) + half_uv[:, 1] * np.abs(sn)
    ey = half_uv[:, 0] * np.abs(sn) + half_uv[:, 1] * np.abs(c)
    i0, i1 = _index_range(center_xy[:, 0] - ex, center_xy[:, 0] + ex, grid.x_min, s, nx)
    j0, j1 = _index_range(center_xy[:, 1] - ey, center_xy[:, 1] + ey, grid.y_min, s, ny)
    k0, k1 = _index_range(z0, z1, grid.z_min, s, nz)
    ni = np.maximum(i1 - i0 + 1, 0)
    nj = np.maximum(j1 - j0 + 1, 0)
    nk = np.maximum(k1 - k0 + 1, 0)
    counts = np.where(nk > 0, ni * nj, 0)
    owner, r = _ragged_offsets(counts)
    ii = i0[owner] + r // nj[owner]
    jj = j0[owner] + r % nj[owner]
    dx = grid.x_min + (ii + 0.5) * s - center_xy[owner, 0]
    dy = grid.y_min + (jj + 0.5) * s - center_xy[owner, 1]
    co, so = c[owner], sn[owner]
    reach = h * (np.abs(co) + np.abs(so))  # the square's half projection on u and on v (same for both)
    keep = (np.abs(dx * co + dy * so) <= half_uv[owner, 0] + reach + _EPS) & \
           (np.abs(-dx * so + dy * co) <= half_uv[owner, 1] + reach + _EPS)
    owner, ii, jj = owner[keep], ii[keep], jj[keep]
    column = ii * ny + jj
    owner_k, rk = _ragged_offsets(nk[owner])
    flat = column[owner_k] * nz + k0[owner[owner_k]] + rk
    return flat, owner[owner_k]


def triangle_voxel_hits(triangles: np.ndarray, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Voxels hit by N triangles (N, 3, 3) given in the grid frame (metres).

    Separating axes: the grid axes (via the exact half-open candidate ranges), the triangle normal and the
    9 cross products of grid axes with triangle edges. Returns (flat voxel index (M,), triangle index (M,)).
    """
    tri = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    n = np.array(grid.shape)
    s, h = grid.voxel_size, grid.voxel_size / 2.0
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    ranges = [_index_range(lo[:, a], hi[:, a], grid.lower[a], s, int(n[a])) for a in range(3)]
    sizes = np.stack([np.maximum(last - first + 1, 0) for first, last in ranges], axis=1)
    owner, r = _ragged_offsets(sizes.prod(axis=1))
    nyz = sizes[owner, 1] * sizes[owner, 2]
    idx = np.stack([
        ranges[0][0][owner] + r // nyz,
        ranges[1][0][owner] + (r % nyz) // sizes[owner, 2],
        ranges[2][0][owner] + r % sizes[owner, 2],
    ], axis=1)
    centers = grid.lower + (idx + 0.5) * s
    edges = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]], axis=1)  # (N,3,3)
    unit = np.eye(3)
    cross_axes = np.cross(unit[None, :, None, :], edges[:, None, :, :]).reshape(-1, 9, 3)
    normal = np.cross(edges[:, 0], edges[:, 1])[:, None, :]
    axes = np.concatenate([cross_axes, normal], axis=1)  # (N, 10, 3)
    proj = np.einsum("nad,nkd->nak", axes, tri)  # (N, 10, 3) projections of the vertices
    pmin, pmax = proj.min(axis=2), proj.max(axis=2)
    radius = h * np.abs(axes).sum(axis=2)  # (N, 10)
    pc = np.einsum("mad,md->ma", axes[owner], centers)
    separated = (pmin[owner] - pc > radius[owner] + _EPS) | (pmax[owner] - pc < -radius[owner] - _EPS)
    keep = ~separated.any(axis=1)
    idx, owner = idx[keep], owner[keep]
    flat = (idx[:, 0] * n[1] + idx[:, 1]) * n[2] + idx[:, 2]
    return flat, owner


def reduce_labels(flat: np.ndarray, rank: np.ndarray, label: np.ndarray, instance: np.ndarray,
                  grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Semantics (uint8) and instance (uint16) grids from labelled voxel hits.

    Per voxel the hit with the highest (rank, instance) wins, and semantics and instance come from the
    same hit. flat, rank, label, instance: (M,) arrays (rank small non-negative ints).
    """
    size = int(np.prod(grid.shape))
    key = (np.asarray(rank, np.int64) << 24) | (np.asarray(instance, np.int64) << 8) | np.asarray(label, np.int64)
    combined = np.sort((np.asarray(flat, np.int64) << 32) | key)  # by voxel, then by key
    last = np.r_[combined[1:] >> 32 != combined[:-1] >> 32, True] if len(combined) else np.zeros(0, bool)
    voxel, best = combined[last] >> 32, combined[last] & 0xFFFFFFFF
    semantics = np.zeros(size, np.uint8)
    instance_grid = np.zeros(size, np.uint16)
    semantics[voxel] = best & 0xFF
    instance_grid[voxel] = (best >> 8) & 0xFFFF
    semantics, instance_grid = semantics.reshape(grid.shape), instance_grid.reshape(grid.shape)
    return semantics, instance_grid


def slab_interval(origins: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t_near, t_far) (N,) of the lines origins + t * dirs (N, 3) through the box [lo, hi]; the line meets
    the box where t_near <= t_far. An axis with dirs == 0 contributes (-inf, inf) if the origin's
    coordinate lies in [lo, hi) and (inf, -inf) otherwise."""
    inside = (origins >= lo) & (origins < hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_a, t_b = (lo - origins) / dirs, (hi - origins) / dirs
    t_near = np.where(dirs == 0, np.where(inside, -np.inf, np.inf), np.minimum(t_a, t_b)).max(axis=1)
    t_far = np.where(dirs == 0, np.where(inside, np.inf, -np.inf), np.maximum(t_a, t_b)).min(axis=1)
    return t_near, t_far


def segment_voxels(origins: np.ndarray, ends: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Flat indices of every voxel traversed by the segments origins[n] -> ends[n] (both (N, 3), grid frame).

    Exact traversal: each segment is clipped to the grid box, then every crossing of a voxel plane along
    x, y and z is enumerated; the voxel entered at each crossing plus the first voxel are the traversed
    voxels (duplicates possible). The end point's voxel is included when it lies inside the grid.
    Per-crossing arithmetic is float32 in voxel units (grid coordinates below 2^10: error < 1e-4 voxel).
    """
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    e = np.asarray(ends, np.float64).reshape(-1, 3)
    d = e - o
    n = np.array(grid.shape)
    s = grid.voxel_size
    lower, upper = grid.lower, grid.upper
    t_near, t_far = slab_interval(o, d, lower, upper)
    t0 = np.maximum(t_near, 0.0)
    t1 = np.minimum(t_far, 1.0)
    valid = t0 <= t1
    a = (o[valid] + t0[valid, None] * d[valid] - lower) / s  # clipped start, voxel units
    b = (o[valid] + t1[valid, None] * d[valid] - lower) / s  # clipped end, voxel units
    start = np.clip(np.floor(a).astype(np.int64), 0, n - 1)
    stop = np.clip(np.floor(b).astype(np.int64), 0, n - 1)
    strides = np.array([n[1] * n[2], n[2], 1], dtype=np.int64)
    pieces = [start @ strides]
    end_inside = np.all((e >= lower) & (e < upper), axis=1)
    pieces.append(np.clip(np.floor((e[end_inside] - lower) / s).astype(np.int64), 0, n - 1) @ strides)
    db = b - a
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        count = np.abs(stop[:, axis] - start[:, axis])
        has = count > 0
        if not has.any():
            continue
        count, st, sa, sb = count[has], start[has], a[has], db[has]
        step = np.sign(sb[:, axis]).astype(np.int64)
        first_plane = st[:, axis] + (step > 0)  # voxel-unit coordinate of the first plane crossed
        # crossing r (0-based): enters index st + step * (r + 1) along `axis`; at that plane the other
        # coordinate k is c0_k + r * dc_k (linear in r)
        f0 = ((st[:, axis] + step) * strides[axis]).astype(np.int32)
        fs = (step * strides[axis]).astype(np.int32)
        owner = np.repeat(np.arange(len(count), dtype=np.int32), count)
        r = np.arange(len(owner), dtype=np.int32)
        r -= (np.cumsum(count) - count).astype(np.int32)[owner]
        flat = fs[owner]
        flat *= r
        flat += f0[owner]
        rf = r.astype(np.float32)
        for k in others:
            beta = sb[:, k] / sb[:, axis]
            c0 = (sa[:, k] + (first_plane - sa[:, axis]) * beta).astype(np.float32)
            coord = (step * beta).astype(np.float32)[owner]
            coord *= rf
            coord += c0[owner]
            np.floor(coord, out=coord)
            idx = coord.astype(np.int32)
            np.clip(idx, 0, np.int32(n[k] - 1), out=idx)
            idx *= np.int32(strides[k])
            flat += idx
        pieces.append(flat)
    return np.concatenate([p.astype(np.int32, copy=False) for p in pieces])
