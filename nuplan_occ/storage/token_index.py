"""Finding rows by string key (a frame's token) without a Python loop over rows or keeping the strings.

`TokenIndex(tokens)` keeps a 64-bit hash of every row's string, sorted once (`string_hashes`: the
UTF-8 bytes in 8-byte words through the splitmix64 finalizer, seeded with the length);
`candidates(token)` binary-searches it and returns the rows whose hash equals the token's, which the
caller compares with the token itself (distinct strings can share a hash).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

_WORD = 8


def _mix(h: np.ndarray) -> np.ndarray:
    """splitmix64 finalizer, elementwise on uint64 (wrapping arithmetic)."""
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def _byte_matrix(values: pa.Array, length: int) -> np.ndarray:
    """(n, length) uint8 bytes of a string array whose every value is `length` bytes long."""
    offsets_type = np.int64 if pa.types.is_large_string(values.type) else np.int32
    _, offsets, data = values.buffers()
    start = int(np.frombuffer(offsets, dtype=offsets_type, count=1, offset=values.offset * np.dtype(offsets_type).itemsize)[0])
    if length == 0:
        return np.zeros((len(values), 0), dtype=np.uint8)
    return np.frombuffer(data, dtype=np.uint8, count=len(values) * length, offset=start).reshape(len(values), length)


def _fixed_length_hashes(matrix: np.ndarray) -> np.ndarray:
    n, length = matrix.shape
    width = -(-length // _WORD) * _WORD
    if width != length:
        matrix = np.concatenate([matrix, np.zeros((n, width - length), dtype=np.uint8)], axis=1)
    words = np.ascontiguousarray(matrix).view("<u8")
    h = _mix(np.full(n, length, dtype=np.uint64))
    for j in range(words.shape[1]):
        h = _mix(h ^ words[:, j])
    return h


def string_hashes(values: pa.Array | pa.ChunkedArray) -> np.ndarray:
    """(n,) uint64 hash of every string (a null hashes as the empty string)."""
    if isinstance(values, pa.ChunkedArray):
        values = values.combine_chunks()
    if values.null_count:
        values = pc.fill_null(values, "")
    lengths = pc.binary_length(values).to_numpy(zero_copy_only=False)
    hashes = np.empty(len(values), dtype=np.uint64)
    for length in np.unique(lengths):
        rows = np.flatnonzero(lengths == length)
        same = values if len(rows) == len(values) else values.take(pa.array(rows))
        hashes[rows] = _fixed_length_hashes(_byte_matrix(same, int(length)))
    return hashes


class TokenIndex:
    """Rows of a string column by value; see the module docstring."""

    def __init__(self, tokens: pa.Array | pa.ChunkedArray):
        hashes = string_hashes(tokens)
        self._order = np.argsort(hashes)
        self._sorted = hashes[self._order]

    def candidates(self, token: str) -> np.ndarray:
        """Ascending rows (int64) whose string may equal `token`: every row that does, maybe others."""
        h = string_hashes(pa.array([token], pa.string()))[0]
        lo, hi = np.searchsorted(self._sorted, h, side="left"), np.searchsorted(self._sorted, h, side="right")
        return np.sort(self._order[lo:hi]).astype(np.int64)
