"""Clusters of sparse voxels: voxels whose Chebyshev distance (in whole voxels) is at most `reach` join one
cluster, transitively. This is the partition that labeling the voxels dilated by a cube of half-width h with
26-connectivity gives for reach = 2h + 1, computed over the voxels themselves instead of a dense volume
(a frame's few thousand voxels may span the whole grid)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _root(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(cache=True)
def _join_within(local: np.ndarray, slot: np.ndarray, reach: int, parent: np.ndarray) -> None:
    """Union every pair of voxels (rows of local, non-negative [x, y, z]) at most reach apart per axis; slot
    maps a voxel of the bounding volume to its row (-1: empty). Each pair is visited from its lower voxel
    in (x, y, z) order only."""
    nx, ny, nz = slot.shape
    for row in range(local.shape[0]):
        x, y, z = local[row, 0], local[row, 1], local[row, 2]
        for dx in range(0, reach + 1):
            px = x + dx
            if px >= nx:
                break
            for dy in range(-reach, reach + 1):
                py = y + dy
                if py < 0 or py >= ny or (dx == 0 and dy < 0):
                    continue
                for dz in range(-reach, reach + 1):
                    pz = z + dz
                    if pz < 0 or pz >= nz or (dx == 0 and dy == 0 and dz <= 0):
                        continue
                    other = slot[px, py, pz]
                    if other >= 0:
                        a, b = _root(parent, row), _root(parent, other)
                        if a != b:
                            parent[max(a, b)] = min(a, b)


@numba.njit(cache=True)
def _roots(parent: np.ndarray) -> np.ndarray:
    """(K,) the root of every element of the union-find forest `parent` (the smallest index of its set)."""
    out = np.empty(len(parent), dtype=np.int64)
    for i in range(len(parent)):
        out[i] = _root(parent, i)
    return out


def chebyshev_clusters(indices: np.ndarray, reach: int) -> tuple[np.ndarray, int]:
    """(labels (K,) int64 in [0, count), count) for the distinct voxels indices (K, 3) int: voxels at most
    reach voxels apart along every axis share a label, transitively. Labels are numbered in the order of
    each cluster's first voxel in `indices`."""
    indices = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    if not len(indices):
        return np.zeros(0, np.int64), 0
    local = indices - indices.min(axis=0)
    slot = np.full(tuple(local.max(axis=0) + 1), -1, dtype=np.int32)
    slot[tuple(local.T)] = np.arange(len(local), dtype=np.int32)
    parent = np.arange(len(local), dtype=np.int64)
    _join_within(local, slot, int(reach), parent)
    first, labels = np.unique(_roots(parent), return_inverse=True)
    return labels.reshape(-1).astype(np.int64), len(first)
