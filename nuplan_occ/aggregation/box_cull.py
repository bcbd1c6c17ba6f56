"""Which segments can cross an upright box: a compiled slab test on a slightly grown box, used to pick the
few candidates of many segments that an exact (numpy) test then decides.

Frames: segments and box in one frame, the box given by its centre, yaw about z and half-size; metres.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _slab(start: float, end: float, half: float, lo: float, hi: float) -> tuple[float, float]:
    """[lo, hi] narrowed to the t of start + t (end - start) within [-half, half] on one axis."""
    d = end - start
    if d == 0.0:
        return (lo, hi) if abs(start) <= half else (1.0, 0.0)
    ta, tb = (-half - start) / d, (half - start) / d
    return max(lo, min(ta, tb)), min(hi, max(ta, tb))


@numba.njit(cache=True)
def segments_near_box(starts: np.ndarray, ends: np.ndarray, center: np.ndarray, yaw: float, half: np.ndarray,
                      grow_m: float) -> np.ndarray:
    """(N,) bool: the segments start -> end (N, 3) with a part of positive length inside the box of half-size
    half (3,) grown by grow_m on every side, centred at center (3,) and turned by yaw (rad) about z.
    Every segment that crosses the box itself is among them when grow_m exceeds the rounding of the
    arithmetic (for coordinates of kilometres, 1e-6 m is ample)."""
    c, s = math.cos(yaw), math.sin(yaw)
    hx, hy, hz = half[0] + grow_m, half[1] + grow_m, half[2] + grow_m
    out = np.zeros(len(ends), dtype=np.bool_)
    for i in range(len(ends)):
        ax, ay, az = starts[i, 0] - center[0], starts[i, 1] - center[1], starts[i, 2] - center[2]
        bx, by, bz = ends[i, 0] - center[0], ends[i, 1] - center[1], ends[i, 2] - center[2]
        lo, hi = _slab(az, bz, hz, 0.0, 1.0)
        if lo >= hi:
            continue
        lo, hi = _slab(ax * c + ay * s, bx * c + by * s, hx, lo, hi)
        if lo >= hi:
            continue
        lo, hi = _slab(-ax * s + ay * c, -bx * s + by * c, hy, lo, hi)
        out[i] = lo < hi
    return out
