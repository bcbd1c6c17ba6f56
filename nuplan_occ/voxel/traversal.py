"""Exact voxel traversal of line segments through the grid (numba kernels, one segment at a time).

A segment from a to b (ego metres) is o + t d, t in [0, 1], in voxel units (o = (a - lower) / voxel_size,
d = (b - lower) / voxel_size - o); it is clipped to the grid box [0, shape] to t in [t0, t1). The voxels
it passes through are its entries: the voxel at its clipped start (entered at t0) and, for every lattice
plane k of an axis it crosses with t = (k - o) / d < t1, the voxel it enters there. An entry's voxel is
the one holding o + (t + nudge) d, nudge = NUDGE_VOXELS / |d| (a hair after the crossing), evaluated
per axis in floating point; entries whose voxel lies outside the grid are dropped. Slivers shorter than
NUDGE_VOXELS (two planes crossed within the nudge) are therefore skipped; where a segment crosses two
planes at exactly the same t (through a lattice edge) both entries give the diagonal voxel, never a
corner neighbour.

The crossings of one axis are walked in order of t ((k - o) / d is monotonic in k), so a walk stops at
the first t >= t1, or at the first occupied voxel (`mark_visible_to_first_hit`). Every crossing time is
computed from its plane index, never accumulated, so the entries do not depend on the walk order.
Flat voxel indices are C order over the grid's (X, Y, Z).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from nuplan_occ.grid import GridSpec

NUDGE_VOXELS = 1e-6
"""How far after a plane crossing (voxels along the segment) its entered voxel is evaluated."""


def grid_args(grid: GridSpec) -> tuple[np.ndarray, float, np.ndarray]:
    """(lower corner (3,) m, voxel size m, shape (3,) int64) of `grid`, as the kernels take them."""
    return grid.lower, float(grid.voxel_size), np.asarray(grid.shape, dtype=np.int64)


@numba.njit(cache=True)
def _setup(start, end, lower, voxel_size, shape, o, d, first, last):
    """Fill o, d (voxel units), first, last (planes crossed per axis, within [0, shape]; unused where d is 0)
    of the segment start -> end (3,) m; returns (t0, t1, nudge / |d|), t0 >= t1 when it misses the grid box or is not
    finite."""
    t0, t1 = 0.0, 1.0
    for a in range(3):
        o[a] = (start[a] - lower[a]) / voxel_size
        d[a] = (end[a] - lower[a]) / voxel_size - o[a]
        if not (math.isfinite(o[a]) and math.isfinite(d[a])):
            return np.inf, -np.inf, 0.0
        if d[a] == 0.0:
            if not (o[a] >= 0.0 and o[a] < shape[a]):
                t0 = np.inf
            continue
        ta = (0.0 - o[a]) / d[a]
        tb = (shape[a] - o[a]) / d[a]
        t0 = max(t0, min(ta, tb))
        t1 = min(t1, max(ta, tb))
    if not t0 < t1:
        return t0, t1, 0.0
    for a in range(3):
        p, q = o[a] + t0 * d[a], o[a] + t1 * d[a]
        first[a] = max(math.floor(min(p, q)) + 1, 0)  # planes beyond [0, shape] enter no voxel of the grid
        last[a] = min(math.floor(max(p, q)), shape[a])
    norm = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return t0, t1, NUDGE_VOXELS / max(norm, 1e-12)


@numba.njit(cache=True)
def _entry_voxel(o, d, t, inv, shape):
    """Flat index of the voxel entered at parameter t (-1 outside the grid)."""
    step = t + inv
    x = o[0] + step * d[0]
    y = o[1] + step * d[1]
    z = o[2] + step * d[2]
    if x < 0.0 or x >= shape[0] or y < 0.0 or y >= shape[1] or z < 0.0 or z >= shape[2]:
        return -1
    return (int(x) * shape[1] + int(y)) * shape[2] + int(z)


@numba.njit(cache=True)
def _walk_start(d, first, last, a):
    """(first plane, plane step, number of planes) of the crossings of axis a, in order of t."""
    if d[a] > 0.0:
        return first[a], 1, last[a] - first[a] + 1
    if d[a] < 0.0:
        return last[a], -1, last[a] - first[a] + 1
    return 0, 0, 0


@numba.njit(cache=True)
def mark_traversed(starts, ends, lower, voxel_size, shape, out, value):
    """out[v] = value for every entry v of the segments starts -> ends ((N, 3) m; lower, voxel_size,
    shape: `grid_args`; out: flat grid)."""
    o, d = np.empty(3), np.empty(3)
    first, last = np.empty(3, np.int64), np.empty(3, np.int64)
    for r in range(starts.shape[0]):
        t0, t1, inv = _setup(starts[r], ends[r], lower, voxel_size, shape, o, d, first, last)
        if not t0 < t1:
            continue
        v = _entry_voxel(o, d, t0, inv, shape)
        if v >= 0:
            out[v] = value
        for a in range(3):
            k, dk, n = _walk_start(d, first, last, a)
            for _ in range(n):
                t = (k - o[a]) / d[a]
                if t >= t1:
                    break
                v = _entry_voxel(o, d, t, inv, shape)
                if v >= 0:
                    out[v] = value
                k += dk


@numba.njit(cache=True)
def mark_visible_to_first_hit(starts, ends, lower, voxel_size, shape, occupied, t_block, visible):
    """visible[v] = True for the entries v of each segment starts -> ends ((N, 3) m) with t <= t_hit, its
    first blocking entry's t (the least t >= t_block of an entry whose voxel is occupied; all entries when
    none blocks). occupied, visible: flat bool grids; lower, voxel_size, shape: `grid_args`.

    Per segment, each axis' walk is recorded (t, voxel) until its first blocking entry or until past the
    t_hit found so far (the axis with the most crossings first: the others then stop early); the
    recorded entries with t <= t_hit are then marked."""
    o, d = np.empty(3), np.empty(3)
    first, last = np.empty(3, np.int64), np.empty(3, np.int64)
    size = shape.max() + 2
    walk_t, walk_v = np.empty((3, size)), np.empty((3, size), np.int64)
    walked = np.zeros(3, np.int64)
    for r in range(starts.shape[0]):
        t0, t1, inv = _setup(starts[r], ends[r], lower, voxel_size, shape, o, d, first, last)
        if not t0 < t1:
            continue
        t_hit = np.inf
        v_start = _entry_voxel(o, d, t0, inv, shape)
        if v_start >= 0 and occupied[v_start] and t0 >= t_block:
            t_hit = t0
        a0 = 0
        if abs(d[1]) > abs(d[a0]):
            a0 = 1
        if abs(d[2]) > abs(d[a0]):
            a0 = 2
        for i in range(3):
            a = (a0 + i) % 3
            k, dk, n = _walk_start(d, first, last, a)
            m = 0
            for _ in range(n):
                t = (k - o[a]) / d[a]
                if t >= t1 or t > t_hit:
                    break
                v = _entry_voxel(o, d, t, inv, shape)
                walk_t[a, m] = t
                walk_v[a, m] = v
                m += 1
                if v >= 0 and occupied[v] and t >= t_block:
                    t_hit = t
                    break
                k += dk
            walked[a] = m
        if v_start >= 0 and t0 <= t_hit:
            visible[v_start] = True
        for a in range(3):
            for m in range(walked[a]):
                if walk_t[a, m] > t_hit:
                    break
                if walk_v[a, m] >= 0:
                    visible[walk_v[a, m]] = True
