"""Compact, lossless pickling of the numeric arrays in stage outputs, for the stage cache.

A numeric array of at least `MIN_CODED_BYTES` is pickled as its bytes regrouped by significance (byte
shuffle, as Blosc does), column by column for a 2-D array, in the narrowest dtype that holds every value
exactly (float64 -> float32, int64 -> int32 / int16 when nothing changes). zstd then finds the runs
that interleaved float and index bytes hide. Decoding restores the original dtype, shape and values bit
for bit. Bytes per entry, coded and not: the notes of bench/report-scale.md.
"""

from __future__ import annotations

import io
import pickle
from typing import Any, BinaryIO

import numpy as np

MIN_CODED_BYTES = 4096
"""Smaller arrays are pickled as they are: their bytes are not worth a pass."""


def narrowest_exact_dtype(array: np.ndarray) -> np.dtype:
    """The smallest dtype of array's kind that stores every value of `array` unchanged."""
    if array.dtype == np.float64:
        widened = array.astype(np.float32).astype(np.float64)
        same_bits = np.array_equal(widened.view(np.int64), np.ascontiguousarray(array).view(np.int64))
        return np.dtype(np.float32) if same_bits else array.dtype
    if array.dtype.kind == "i" and array.dtype.itemsize > 2 and array.size:
        low, high = int(array.min()), int(array.max())
        for candidate in (np.int16, np.int32):
            bounds = np.iinfo(candidate)
            if candidate().itemsize < array.dtype.itemsize and bounds.min <= low and high <= bounds.max:
                return np.dtype(candidate)
    return array.dtype


def shuffled_bytes(array: np.ndarray) -> bytes:
    """Bytes of a contiguous array regrouped by byte significance: all first bytes, then all second ..."""
    values = np.ascontiguousarray(array).view(np.uint8).reshape(-1, array.dtype.itemsize)
    planes = np.empty(values.shape[::-1], dtype=np.uint8)
    for b in range(array.dtype.itemsize):  # a strided column per pass: faster than a transposed copy
        planes[b] = values[:, b]
    return planes.tobytes()


def restore_array(dtype: str, stored: str, shape: tuple[int, ...], by_column: bool, data: bytes) -> np.ndarray:
    """The array encoded by `encode_array` (the pickle reconstructor)."""
    stored_dtype = np.dtype(stored)
    count = int(np.prod(shape))
    planes = np.frombuffer(data, dtype=np.uint8).reshape(stored_dtype.itemsize, count)
    as_bytes = np.empty((count, stored_dtype.itemsize), dtype=np.uint8)
    for b in range(stored_dtype.itemsize):  # as in shuffled_bytes
        as_bytes[:, b] = planes[b]
    values = as_bytes.view(stored_dtype)
    values = values.reshape(shape[::-1]).T if by_column else values.reshape(shape)
    return np.ascontiguousarray(values.astype(np.dtype(dtype), copy=False))


def encode_array(array: np.ndarray) -> tuple[Any, tuple] | None:
    """The (reconstructor, args) pickle reduction of a numeric array, or None to pickle it as usual."""
    if array.dtype.kind not in "fiub" or array.nbytes < MIN_CODED_BYTES or array.dtype.byteorder == ">":
        return None
    stored = narrowest_exact_dtype(array)
    by_column = array.ndim == 2
    laid_out = (array.T if by_column else array).astype(stored, order="C")
    return restore_array, (array.dtype.str, stored.str, array.shape, by_column, shuffled_bytes(laid_out))


class _ArrayPickler(pickle.Pickler):
    def reducer_override(self, obj: Any) -> Any:
        if type(obj) is np.ndarray:
            reduction = encode_array(obj)
            if reduction is not None:
                return reduction
        return NotImplemented


def dump(obj: Any, file: BinaryIO) -> None:
    """Write pickle protocol 5 of obj, its numeric arrays encoded compactly, to `file` (pickle.load reads it).

    Without a memo: neither the pickler nor the unpickler then holds every encoded array until the end, so
    writing or reading an entry costs about one array beyond the objects themselves. An object reached
    twice is stored twice (and read back as two equal objects); obj must not contain itself."""
    pickler = _ArrayPickler(file, protocol=5)
    pickler.fast = True
    pickler.dump(obj)


def dumps(obj: Any) -> bytes:
    """`dump` into bytes."""
    buffer = io.BytesIO()
    dump(obj, buffer)
    return buffer.getvalue()
