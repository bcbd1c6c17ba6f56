"""Exact voxel traversal of line segments through the grid (numba kernels, one segment at a time).

A segment from a to b (ego metres) is o + t d, t in [0, 1], in voxel units (o = (a - lower) / voxel_size,
d = (b - lower) / voxel_size - o); it is clipped to the grid box [0, shape] to t in [t0, t1). The voxels
it passes through are its entries: the voxel at its clipped start (entered at t0) and, for every lattice
plane k of an axis it crosses with t = (k - o) * (1 / d) < t1 (the reciprocal taken once per segment and
axis), the voxel it enters there. An entry's voxel is the one holding o + (t + nudge) d, nudge =
NUDGE_VOXELS / |d| (a hair after the crossing, far more than the reciprocal's rounding), evaluated per axis
in floating point; entries whose voxel lies outside the grid are dropped. Slivers shorter than
NUDGE_VOXELS (two planes crossed within the nudge) are therefore skipped; where a segment crosses two
planes at exactly the same t (through a lattice edge) both entries give the diagonal voxel, never a
corner neighbour.

The crossings of one axis are in order of t ((k - o) / d is monotonic in k). `mark_traversed` computes
them axis by axis, WALK_PAD at a time in branch-free (vectorized) runs; `mark_visible_to_first_hit` merges
the three axes' crossings in order of t, so a camera ray stops at its first occupied voxel without
computing any crossing beyond it. Every crossing time is computed from its plane index, never accumulated,
so the entries do not depend on the walk order. Flat voxel indices are C order over the grid's (X, Y, Z).

The merged walk also counts the voxel it is in (each crossing steps one axis's cell), and takes that count
as the entry's voxel where the floating-point evaluation above cannot differ from it: no other axis's
plane is crossed within the nudge plus SAFE_VOXELS (in that axis's voxels) of the entry, the crossing axis
moves more than SAFE_VOXELS within the nudge, the entry is not within such a window of the walk's start or
end, and every cell is inside the grid. Elsewhere (through a lattice edge, grazing a plane, at the border) it
evaluates the entry as above, so the entries are the same.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from nuplan_occ.grid import GridSpec

NUDGE_VOXELS = 1e-6
"""How far after a plane crossing (voxels along the segment) its entered voxel is evaluated."""

WALK_PAD = 16
"""Crossings are computed in whole runs of this many (a multiple of the SIMD width)."""


SAFE_VOXELS = 1e-9
"""Distance (voxels) from a lattice plane beyond which rounding cannot move a coordinate across it (the
coordinates' rounding is below 1e-12 voxels on grids of up to 2**31 voxels)."""

MAX_VOXELS = 2**31 - 1
"""The kernels' flat voxel indices are int32: a grid holds fewer voxels than this."""


def grid_args(grid: GridSpec) -> tuple[np.ndarray, float, np.ndarray]:
    """(lower corner (3,) m, voxel size m, shape (3,) int64) of `grid`, as the kernels take them; raises
    ValueError for a grid of MAX_VOXELS voxels or more."""
    shape = np.asarray(grid.shape, dtype=np.int64)
    if int(np.prod(shape)) >= MAX_VOXELS:
        raise ValueError(f"grid of {grid.shape} voxels: the traversal kernels index fewer than {MAX_VOXELS}")
    return grid.lower, float(grid.voxel_size), shape


@numba.njit(cache=True, inline="always")
def _axis(start, end, lower, voxel_size, n):
    """o, d (voxel units) of one axis of the segment start -> end (m) and its parameter interval
    [t_lo, t_hi] inside [0, n] (all t, or none, where d is 0)."""
    o = (start - lower) / voxel_size
    d = (end - lower) / voxel_size - o
    if d == 0.0:
        if o >= 0.0 and o < n:
            return o, d, -np.inf, np.inf
        return o, d, np.inf, -np.inf
    ta = (0.0 - o) / d
    tb = (n - o) / d
    return o, d, min(ta, tb), max(ta, tb)


@numba.njit(cache=True, inline="always")
def _segment(starts, ends, r, lower, voxel_size, shape):
    """(meets the grid box, o (3), d (3), t0, t1, nudge / |d|) of segment r; False for a segment that
    misses the box or is not finite."""
    ox, dx, lx, hx = _axis(starts[r, 0], ends[r, 0], lower[0], voxel_size, shape[0])
    oy, dy, ly, hy = _axis(starts[r, 1], ends[r, 1], lower[1], voxel_size, shape[1])
    oz, dz, lz, hz = _axis(starts[r, 2], ends[r, 2], lower[2], voxel_size, shape[2])
    t0 = max(max(max(lx, ly), lz), 0.0)
    t1 = min(min(min(hx, hy), hz), 1.0)
    finite = (math.isfinite(ox) and math.isfinite(oy) and math.isfinite(oz)
              and math.isfinite(dx) and math.isfinite(dy) and math.isfinite(dz))
    inv = NUDGE_VOXELS / max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
    return finite and t0 < t1, ox, oy, oz, dx, dy, dz, t0, t1, inv


@numba.njit(cache=True, inline="always")
def _planes(o, d, t0, t1, n):
    """(first plane, plane step, number of planes) crossed in order of t by one axis o + t d, t in
    [t0, t1], within [0, n] (planes beyond it enter no voxel of the grid)."""
    if d == 0.0:
        return 0, 0, 0
    p, q = o + t0 * d, o + t1 * d
    first = max(math.floor(min(p, q)) + 1, 0)
    last = min(math.floor(max(p, q)), n)
    count = max(last - first + 1, 0)
    return (first, 1, count) if d > 0.0 else (last, -1, count)


@numba.njit(cache=True, inline="always")
def _voxel(ox, oy, oz, dx, dy, dz, t, inv, fx, fy, fz, ny, nz):
    """Flat index of the voxel holding o + (t + inv) d (-1 outside the grid of (fx, fy, fz) voxels)."""
    step = t + inv
    x, y, z = ox + step * dx, oy + step * dy, oz + step * dz
    if x < 0.0 or x >= fx or y < 0.0 or y >= fy or z < 0.0 or z >= fz:
        return -1
    return (int(x) * ny + int(y)) * nz + int(z)


@numba.njit(cache=True, inline="always")
def _walk(oa, rda, k0, dk, n, i0, t1, inv, ox, oy, oz, dx, dy, dz, fx, fy, fz, ny, nz, walk_t, walk_v, base):
    """Record crossings i0 .. i0 + WALK_PAD - 1 (plane k0 + i dk of the axis o_a + t d_a; rda = 1 / d_a) at
    walk_t[base + i], walk_v[base + i]: (t, entered voxel), voxel -1 past the n planes, outside the grid or
    where t >= t1. Branch-free, so it vectorizes."""
    for i in range(i0, i0 + WALK_PAD):
        t = ((k0 + i * dk) - oa) * rda
        step = t + inv
        x, y, z = ox + step * dx, oy + step * dy, oz + step * dz
        inside = (i < n) & (t < t1) & (x >= 0.0) & (x < fx) & (y >= 0.0) & (y < fy) & (z >= 0.0) & (z < fz)
        v = (np.int32(x) * np.int32(ny) + np.int32(y)) * np.int32(nz) + np.int32(z)  # int32: AVX2 converts 4 at once
        walk_t[base + i] = t
        walk_v[base + i] = v if inside else np.int32(-1)


@numba.njit(cache=True, inline="always")
def _set_bit(bits, v):
    """Set voxel v's bit in `bits` (np.packbits order: bit 7 - v % 8 of byte v // 8)."""
    bits[v >> 3] |= np.uint8(128 >> (v & 7))


@numba.njit(cache=True)
def mark_bits(voxels, bits):
    """Set the bits of the flat voxel indices `voxels` in `bits` (packed as `mark_traversed` packs them)."""
    for v in voxels:
        _set_bit(bits, v)


@numba.njit(cache=True)
def mark_traversed(starts, ends, lower, voxel_size, shape, bits):
    """Set the bit of every entry v of the segments starts -> ends ((N, 3) m; lower, voxel_size, shape:
    `grid_args`) in `bits`, the flat grid packed 8 voxels a byte as np.packbits packs it."""
    fx, fy, fz = float(shape[0]), float(shape[1]), float(shape[2])
    ny, nz = shape[1], shape[2]
    walk_t, walk_v = np.empty(WALK_PAD), np.empty(WALK_PAD, np.int32)
    for r in range(starts.shape[0]):
        meets, ox, oy, oz, dx, dy, dz, t0, t1, inv = _segment(starts, ends, r, lower, voxel_size, shape)
        if not meets:
            continue
        v = _voxel(ox, oy, oz, dx, dy, dz, t0, inv, fx, fy, fz, ny, nz)
        if v >= 0:
            _set_bit(bits, v)
        for a in range(3):
            oa, da = (ox, dx) if a == 0 else ((oy, dy) if a == 1 else (oz, dz))
            k0, dk, n = _planes(oa, da, t0, t1, shape[a])
            rda = 1.0 / da if n else 0.0
            for i0 in range(0, n, WALK_PAD):
                _walk(oa, rda, k0 + i0 * dk, dk, n - i0, 0, t1, inv, ox, oy, oz, dx, dy, dz, fx, fy, fz, ny, nz,
                      walk_t, walk_v, 0)
                for m in range(WALK_PAD):
                    if walk_v[m] >= 0:
                        _set_bit(bits, walk_v[m])


@numba.njit(cache=True, inline="always")
def _crossing(k0, dk, i, n, oa, rda, t1):
    """t of crossing i (plane k0 + i dk of the axis o_a + t d_a; rda = 1 / d_a) of an axis with n crossings,
    inf past the last one or at t >= t1."""
    if i >= n:
        return np.inf
    t = ((k0 + i * dk) - oa) * rda
    return t if t < t1 else np.inf


@numba.njit(cache=True, inline="always")
def _cell_before(o, d, t0, k0, n):
    """The cell index of the axis o + t d before its first crossing (plane k0 of n crossings, see `_planes`),
    or where the walk starts (t0) when it crosses none."""
    if n == 0:
        return math.floor(o + t0 * d)
    return k0 - 1 if d > 0.0 else k0


@numba.njit(cache=True, inline="always")
def _margin(d, inv):
    """The t window around a plane crossing of axis velocity d within which an entry is evaluated in floating
    point: the nudge plus SAFE_VOXELS of that axis (-inf for an axis that does not move: it crosses none)."""
    return inv + SAFE_VOXELS / abs(d) if d != 0.0 else -np.inf


@numba.njit(cache=True, inline="always")
def _inside(cx, cy, cz, nx, ny, nz):
    """Whether the cell (cx, cy, cz) lies in a grid of (nx, ny, nz) voxels."""
    return 0 <= cx < nx and 0 <= cy < ny and 0 <= cz < nz


@numba.njit(cache=True)
def mark_visible_to_first_hit(starts, ends, lower, voxel_size, shape, occupied, t_block, from_t, visible, reached,
                              stop_t):
    """visible[v] = True for the entries v of each segment starts -> ends ((N, 3) m) with from_t[r] <= t <= t_hit,
    its first blocking entry's t (the least t >= t_block of an entry whose voxel is occupied; all entries when
    none blocks). Segment r is walked from t = from_t[r] on (the part before stands for one that other rays
    walked), and not at all where from_t[r] is inf. For a walked segment, reached[r] = True when it ends
    (t = 1) inside the grid with no blocking entry, and stop_t[r] is where its walk ended: t_hit, or where it
    leaves the grid or ends (within [0, 1]; 0 for one missing the grid); a segment not walked gets reached[r] = False and keeps its stop_t.
    occupied, visible: flat bool grids; lower, voxel_size, shape: `grid_args`.

    Per segment, the three axes' crossings are merged in order of t (the next one of each axis computed from
    its plane index), each entry marked as it is reached, until the first entry past t_hit; the entry's voxel
    is the counted cell where that is safe (module doc)."""
    fx, fy, fz = float(shape[0]), float(shape[1]), float(shape[2])
    nx_, ny, nz = shape[0], shape[1], shape[2]
    for r in range(starts.shape[0]):
        reached[r] = False
        if from_t[r] == np.inf:
            continue
        meets, ox, oy, oz, dx, dy, dz, t0, t1, inv = _segment(starts, ends, r, lower, voxel_size, shape)
        t0 = max(t0, from_t[r])
        stop_t[r] = min(max(t1, 0.0), 1.0) if meets else 0.0
        if not meets or t0 >= t1:
            continue
        t_hit = np.inf
        v = _voxel(ox, oy, oz, dx, dy, dz, t0, inv, fx, fy, fz, ny, nz)
        if v >= 0:
            visible[v] = True
            if occupied[v] and t0 >= t_block:
                t_hit = t0
        kx, sx, nx = _planes(ox, dx, t0, t1, shape[0])
        ky, sy, my = _planes(oy, dy, t0, t1, shape[1])
        kz, sz, mz = _planes(oz, dz, t0, t1, shape[2])
        rx, ry, rz = (1.0 / dx if nx else 0.0), (1.0 / dy if my else 0.0), (1.0 / dz if mz else 0.0)
        cx, cy, cz = _cell_before(ox, dx, t0, kx, nx), _cell_before(oy, dy, t0, ky, my), _cell_before(oz, dz, t0, kz, mz)
        cell = (cx * ny + cy) * nz + cz  # meaningful while every cell is inside the grid
        wx, wy, wz = _margin(dx, inv), _margin(dy, inv), _margin(dz, inv)
        safe_end = t1 - max(wx, wy, wz)  # past it, a plane beyond the segment's end may lie within a window
        evaluate = not _inside(cx, cy, cz, nx_, ny, nz) or (
            (nx > 0 and inv * abs(dx) <= SAFE_VOXELS) or (my > 0 and inv * abs(dy) <= SAFE_VOXELS)
            or (mz > 0 and inv * abs(dz) <= SAFE_VOXELS))
        px = py = pz = t0  # each axis's last crossing (t0 before its first)
        ix = iy = iz = 0
        tx, ty, tz = _crossing(kx, sx, 0, nx, ox, rx, t1), _crossing(ky, sy, 0, my, oy, ry, t1), _crossing(kz, sz, 0, mz, oz, rz, t1)
        while True:
            if tx <= ty and tx <= tz:
                t = px = tx
                ix += 1
                tx = _crossing(kx, sx, ix, nx, ox, rx, t1)
                cx += sx
                cell += sx * ny * nz
                near = (ty - t < wy) | (t - py < wy) | (tz - t < wz) | (t - pz < wz) | (cx < 0) | (cx >= nx_)
            elif ty <= tz:
                t = py = ty
                iy += 1
                ty = _crossing(ky, sy, iy, my, oy, ry, t1)
                cy += sy
                cell += sy * nz
                near = (tx - t < wx) | (t - px < wx) | (tz - t < wz) | (t - pz < wz) | (cy < 0) | (cy >= ny)
            else:
                t = pz = tz
                iz += 1
                tz = _crossing(kz, sz, iz, mz, oz, rz, t1)
                cz += sz
                cell += sz
                near = (tx - t < wx) | (t - px < wx) | (ty - t < wy) | (t - py < wy) | (cz < 0) | (cz >= nz)
            if t > t_hit or t == np.inf:
                break
            if near | evaluate | (t > safe_end):  # bitwise: no branch per test
                v = _voxel(ox, oy, oz, dx, dy, dz, t, inv, fx, fy, fz, ny, nz)
                evaluate = evaluate or not _inside(cx, cy, cz, nx_, ny, nz)
            else:
                v = cell
            if v >= 0:
                visible[v] = True
                if t_hit == np.inf and occupied[v] and t >= t_block:
                    t_hit = t
        reached[r] = t_hit == np.inf and t1 >= 1.0
        stop_t[r] = min(t_hit, stop_t[r])
