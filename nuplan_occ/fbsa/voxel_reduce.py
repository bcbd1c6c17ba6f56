"""Reductions of a point set over a voxel grid: cubes of edge voxel_m aligned with the origin of the points'
frame (voxel (i, j, k) = [i, i + 1) x [j, j + 1) x [k, k + 1) times voxel_m; metres).

Voxels are named by one int64 packing their three indices (`voxel_keys`), which orders them by i, then j,
then k; indices must lie in [-2^20, 2^20), i.e. within +-2^20 voxel_m of the origin (about 200 km at
0.2 m).
"""

from __future__ import annotations

import numba
import numpy as np

from nuplan_occ.fbsa import FbsaInputError

KEY_BITS = 21
"""Bits per voxel index in a packed key (three of them fit in an int64)."""


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) int64 packed voxel key of each point (N, 3); raises FbsaInputError beyond the packable range."""
    index = np.floor(np.asarray(points, np.float64).reshape(-1, 3) / voxel_m)
    half = float(1 << (KEY_BITS - 1))
    if len(index) and (index.min() < -half or index.max() >= half):
        raise FbsaInputError(f"voxel_keys: points reach {np.abs(points).max():.0f} m from the origin, beyond the "
                             f"{half * voxel_m:.0f} m that {voxel_m} m voxels can name")
    shifted = index.astype(np.int64) + (1 << (KEY_BITS - 1))
    return (shifted[:, 0] << (2 * KEY_BITS)) | (shifted[:, 1] << KEY_BITS) | shifted[:, 2]


def voxel_centroids(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(K, 3) mean of the points (N, 3) of each occupied voxel, one row per voxel in key order."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(pts):
        return np.zeros((0, 3))
    keys = voxel_keys(pts, voxel_m)
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    counts = np.diff(np.r_[starts, len(ordered)])
    return np.add.reduceat(pts[order], starts, axis=0) / counts[:, None]



@numba.njit(cache=True)
def first_of_each_key(keys: np.ndarray) -> np.ndarray:
    """Ascending (K,) indices of the first occurrence of every distinct value of keys (N,) int64 (an open
    addressing hash table: linear time, the same answer as np.sort(np.unique(keys, return_index=True)[1]))."""
    n = len(keys)
    bits = 1
    while (1 << bits) < 2 * n:
        bits += 1
    mask = np.uint64((1 << bits) - 1)
    shift = np.uint64(64 - bits)
    table = np.full(1 << bits, -1, np.int64)
    first = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        slot = (np.uint64(keys[i]) * np.uint64(0x9E3779B97F4A7C15)) >> shift  # Fibonacci hashing
        while True:
            j = table[slot]
            if j < 0:
                table[slot] = i
                first[count] = i
                count += 1
                break
            if keys[j] == keys[i]:
                break
            slot = (slot + np.uint64(1)) & mask
    return first[:count]
