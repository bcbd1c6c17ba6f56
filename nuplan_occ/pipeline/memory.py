"""The C heap of a build worker: freed pages kept for the next frame, and handed back between stages.

A frame allocates and frees tens of MB of grids (5 MB per bool or uint8 grid, 10 MB instance ids, 31 MB
flow). With glibc's defaults, blocks above an adaptive threshold (at most 32 MB) are mapped and unmapped
each time, and the heap's free top is handed back once it passes twice that threshold: every frame then
faults its grids' pages in again, one zero-filled 4 KB page at a time. `reuse_freed_pages` keeps such
blocks in the heap, so the next frame reuses the same pages (the system time and page faults it saves are in
bench/report-scale.md's notes); `release_free_memory` still returns the free pages to the OS after every
stage, so an earlier stage's peak is not carried into the next. Elsewhere (another libc, another OS) both
are no-ops.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import lru_cache

MMAP_THRESHOLD_BYTES = 64 << 20
"""Blocks smaller than this come from the heap (glibc M_MMAP_THRESHOLD): every per-frame grid."""
TRIM_THRESHOLD_BYTES = 256 << 20
"""The heap hands its free top back to the OS by itself only beyond this (glibc M_TRIM_THRESHOLD)."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h> mallopt parameters


@lru_cache(maxsize=1)
def _libc():
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        if libc is None or not hasattr(libc, "malloc_trim") or not hasattr(libc, "mallopt"):
            return None
    except OSError:
        return None
    libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
    libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return libc


def release_free_memory() -> bool:
    """Return the heap's free pages to the OS (glibc malloc_trim(0)); False where unavailable."""
    libc = _libc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


def reuse_freed_pages() -> bool:
    """For the rest of this process, keep freed blocks below MMAP_THRESHOLD_BYTES in the heap and its free top
    up to TRIM_THRESHOLD_BYTES (glibc mallopt; this also fixes the thresholds, which glibc otherwise adapts);
    True when applied, False where unavailable."""
    libc = _libc()
    if libc is None:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) and libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
