"""Lexicographic order of integer key columns (the first key most significant), as numpy arrays.

Manifests and clip indexes are nearly always stored in key order already, so the order is checked
first (a pass over the keys) and sorted (a stable `np.lexsort`) only when it is not.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def in_order(keys: Sequence[np.ndarray]) -> bool:
    """True if the rows (element i of every key) are in non-decreasing lexicographic order."""
    if not keys or len(keys[0]) < 2:
        return True
    undecided = np.ones(len(keys[0]) - 1, dtype=bool)
    for key in keys:
        before, after = key[:-1], key[1:]
        if np.any(undecided & (before > after)):
            return False
        undecided &= before == after
    return True


def lex_order(keys: Sequence[np.ndarray]) -> np.ndarray:
    """Row indices (int64) in stable lexicographic order of `keys` (equal keys keep their row order)."""
    n = len(keys[0]) if keys else 0
    if in_order(keys):
        return np.arange(n, dtype=np.int64)
    return np.lexsort(list(keys)[::-1]).astype(np.int64)


def has_ties(keys: Sequence[np.ndarray], order: np.ndarray | None = None) -> bool:
    """True if two rows adjacent in `order` (None: as they are) are equal in every key."""
    n = len(keys[0]) if order is None else len(order)
    if n < 2:
        return False
    equal = np.ones(n - 1, dtype=bool)
    for key in keys:
        ordered = key if order is None else key[order]
        equal &= ordered[1:] == ordered[:-1]
    return bool(equal.any())
