"""Handing freed heap memory back to the operating system between stages.

glibc's malloc keeps freed blocks below its adaptive mmap threshold (up to 32 MB) in the process heap, and
a long scene's stages free GBs of such blocks (per-sweep clouds, encoded cache arrays); without a trim the
worker's resident memory keeps every earlier stage's peak while the frame stream runs (measured in
bench/report-scale.md). Elsewhere (another libc, another OS) this is a no-op.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import lru_cache


@lru_cache(maxsize=1)
def _malloc_trim():
    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def release_free_memory() -> bool:
    """Return the heap's free pages to the OS (glibc malloc_trim(0)); False where unavailable."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
