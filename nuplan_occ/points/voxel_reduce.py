"""Reductions of a point set over a voxel grid: cubes of edge voxel_m aligned with the origin of the points'
frame (voxel (i, j, k) = [i, i + 1) x [j, j + 1) x [k, k + 1) times voxel_m; metres).

Voxels are named by one int64 packing their three indices (`voxel_keys`), which orders them by i, then j,
then k; indices must lie in [-2^20, 2^20), i.e. within +-2^20 voxel_m of the origin (about 200 km at
0.2 m).
"""

from __future__ import annotations

import numba
import numpy as np

from nuplan_occ.points import PointInputError

KEY_BITS = 21
"""Bits per voxel index in a packed key (three of them fit in an int64)."""


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """(N,) int64 packed voxel key of each point (N, 3); raises PointInputError beyond the packable range."""
    pts = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
    keys = np.empty(len(pts), np.int64)
    lowest, highest = _pack_voxel_keys(pts, float(voxel_m), keys)
    half = float(1 << (KEY_BITS - 1))
    if lowest < -half or highest >= half:
        raise PointInputError(f"voxel_keys: points reach {np.abs(pts).max():.0f} m from the origin, beyond the "
                             f"{half * voxel_m:.0f} m that {voxel_m} m voxels can name")
    return keys


@numba.njit(cache=True)
def _pack_voxel_keys(points: np.ndarray, voxel_m: float, keys: np.ndarray) -> tuple[float, float]:
    """Writes to keys (N,) the packed key of each point's voxel index floor(points / voxel_m) (N, 3), in one pass;
    returns the least and the largest index over all axes (inf, -inf for no points), for the range check."""
    lowest, highest = np.inf, -np.inf
    offset = 1 << (KEY_BITS - 1)
    for n in range(points.shape[0]):
        i = np.floor(points[n, 0] / voxel_m)
        j = np.floor(points[n, 1] / voxel_m)
        k = np.floor(points[n, 2] / voxel_m)
        lowest = min(lowest, i, j, k)
        highest = max(highest, i, j, k)
        keys[n] = (((np.int64(i) + offset) << (2 * KEY_BITS)) | ((np.int64(j) + offset) << KEY_BITS)
                   | (np.int64(k) + offset))
    return lowest, highest


def voxel_centroids(points: np.ndarray, voxel_m: float, min_count: int = 1) -> np.ndarray:
    """(K, 3) mean of the points (N, 3) of each voxel holding at least min_count of them, one row per voxel in
    key order."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    index = KeyIndex(voxel_keys(pts, voxel_m))
    order = np.argsort(index.keys)
    means = group_means(index.ids, pts, len(index.keys))[order]
    if min_count <= 1:
        return means
    return means[np.bincount(index.ids, minlength=len(index.keys))[order] >= min_count]


@numba.njit(cache=True)
def group_means(ids: np.ndarray, values: np.ndarray, groups: int) -> np.ndarray:
    """(groups, d) mean of the rows of values (N, d) float64 with each id of ids (N,) int64 in [0, groups)
    (summed in row order; every group must have a row)."""
    sums = np.zeros((groups, values.shape[1]))
    counts = np.zeros(groups)
    for i in range(len(ids)):
        g = ids[i]
        counts[g] += 1.0
        for d in range(values.shape[1]):
            sums[g, d] += values[i, d]
    for g in range(groups):
        for d in range(values.shape[1]):
            sums[g, d] /= counts[g]
    return sums



@numba.njit(cache=True)
def _insert_keys(table: np.ndarray, used: np.ndarray, keys: np.ndarray, first: np.ndarray) -> int:
    """Insert keys (N,) int64 into the open-addressing hash set (table, used): a power-of-two number of key
    slots and whether each holds one, at most half full after the call. Writes to `first` the ascending
    indices of the keys that were not in it yet (each distinct new key once, at its first occurrence) and
    returns how many."""
    bits = 0
    while (1 << bits) < len(table):
        bits += 1
    mask = np.uint64(len(table) - 1)
    shift = np.uint64(64 - bits)
    count = 0
    for i in range(len(keys)):
        slot = (np.uint64(keys[i]) * np.uint64(0x9E3779B97F4A7C15)) >> shift  # Fibonacci hashing
        while True:
            if not used[slot]:
                used[slot] = True
                table[slot] = keys[i]
                first[count] = i
                count += 1
                break
            if table[slot] == keys[i]:
                break
            slot = (slot + np.uint64(1)) & mask
    return count


@numba.njit(cache=True)
def _holds_keys(table: np.ndarray, used: np.ndarray, keys: np.ndarray, bits: int) -> np.ndarray:
    """(N,) bool: whether each of keys (N,) int64 is in the open-addressing hash set (table, used) of 2^bits
    slots filled by `_insert_keys`."""
    mask = np.uint64(len(table) - 1)
    held = np.zeros(len(keys), dtype=np.bool_)
    for i in range(len(keys)):
        slot = _home_slot(keys[i], bits)
        while used[slot]:
            if table[slot] == keys[i]:
                held[i] = True
                break
            slot = (slot + np.uint64(1)) & mask
    return held


def _table_size(keys: int) -> int:
    """Power-of-two hash table length holding `keys` keys at most half full."""
    return 1 << max(4, int(2 * keys - 1).bit_length())


class KeySet:
    """A growing set of int64 keys: `new(keys)` adds a batch and tells which of its keys it did not hold."""

    def __init__(self, capacity: int = 0):
        self.table = np.zeros(_table_size(capacity), np.int64)
        self.used = np.zeros(len(self.table), bool)
        self.count = 0

    def new(self, keys: np.ndarray) -> np.ndarray:
        """Ascending indices of the first occurrence of every value of keys (N,) int64 not in the set before;
        those values are added."""
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        if _table_size(self.count + len(keys)) > len(self.table):
            held = self.table[self.used]
            self.table = np.zeros(_table_size(self.count + len(keys)), np.int64)
            self.used = np.zeros(len(self.table), bool)
            _insert_keys(self.table, self.used, held, np.empty(len(held), np.int64))
        first = np.empty(len(keys), np.int64)
        added = _insert_keys(self.table, self.used, keys, first)
        self.count += added
        return first[:added].copy()

    def holds(self, keys: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each value of keys (N,) int64 is in the set (the same as np.isin against its values)."""
        return _holds_keys(self.table, self.used, np.ascontiguousarray(keys, dtype=np.int64), len(self.table).bit_length() - 1)


def first_of_each_key(keys: np.ndarray) -> np.ndarray:
    """Ascending (K,) indices of the first occurrence of every distinct value of keys (N,) int64 (linear time,
    the same answer as np.sort(np.unique(keys, return_index=True)[1]))."""
    return KeySet(len(keys)).new(keys)




@numba.njit(cache=True)
def _home_slot(key: np.int64, bits: int) -> np.uint64:
    """Home slot of key in a table of 2^bits slots (Fibonacci hashing)."""
    return (np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits)


@numba.njit(cache=True)
def _index_keys(keys: np.ndarray, table: np.ndarray, slot_id: np.ndarray, bits: int, start: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """(ids (N,), first (K,)): the id of each key (N,) int64 in the open-addressing table (key per slot,
    slot_id -1 = empty) of 2^bits slots, which holds ids 0..start-1 and must stay at most half full; keys not
    in it get the ids start, start + 1, ... in order of first occurrence, `first` the index of each new id's
    first occurrence."""
    mask = np.uint64(len(table) - 1)
    ids = np.empty(len(keys), np.int64)
    first = np.empty(len(keys), np.int64)
    count = start
    for i in range(len(keys)):
        slot = _home_slot(keys[i], bits)
        while slot_id[slot] >= 0 and table[slot] != keys[i]:
            slot = (slot + np.uint64(1)) & mask
        if slot_id[slot] < 0:
            table[slot] = keys[i]
            slot_id[slot] = count
            first[count - start] = i
            count += 1
        ids[i] = slot_id[slot]
    return ids, first[:count - start].copy()


@numba.njit(cache=True)
def accumulate(ids: np.ndarray, values: np.ndarray, sign: float, sums: np.ndarray, counts: np.ndarray) -> None:
    """Add (sign 1) or take away (sign -1) the rows of values (N, d) to sums (G, d) and 1 to counts (G,) at the
    ids (N,) int64 in [0, G), in row order; a group whose count returns to 0 gets sums of exactly 0 (no
    rounding residue)."""
    for i in range(len(ids)):
        g = ids[i]
        counts[g] += sign
        for d in range(values.shape[1]):
            sums[g, d] = sums[g, d] + sign * values[i, d] if counts[g] > 0 else 0.0


class KeyIndex:
    """Dense ids of distinct int64 keys: id g names the g-th distinct value in order of first occurrence, over
    the keys (N,) given first and any `add`ed later. `ids` (N,) the id of every key given first; `keys` (K,)
    the distinct values so far (keys[ids] == the keys given first)."""

    def __init__(self, keys: np.ndarray | None = None):
        keys = np.zeros(0, np.int64) if keys is None else keys
        self.keys = np.zeros(0, np.int64)
        self._allocate(len(keys))
        self.ids = self.add(keys)

    def add(self, keys: np.ndarray) -> np.ndarray:
        """(M,) id of each of keys (M,) int64; values not indexed yet get new ids (the index grows)."""
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        if _table_size(len(self.keys) + len(keys)) > len(self._table):
            held = self.keys
            self._allocate(len(held) + len(keys))
            _index_keys(held, self._table, self._slot_id, self._bits, 0)
        ids, first = _index_keys(keys, self._table, self._slot_id, self._bits, len(self.keys))
        self.keys = np.concatenate([self.keys, keys[first]])
        return ids

    def _allocate(self, count: int) -> None:
        """An empty table for `count` keys (the held keys must be inserted again)."""
        size = _table_size(count)
        self._bits = size.bit_length() - 1
        self._table = np.zeros(size, np.int64)
        self._slot_id = np.full(size, -1, np.int64)
