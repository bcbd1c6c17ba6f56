"""Member codecs: how each per-frame array is turned into the bytes of one tar member and back.

Every array member is the dense C-order array (little-endian) compressed as one zstd frame with its
content size in the header, so any zstd decoder reads it. Boolean masks are `np.packbits`-ed first
(1 bit per voxel, C order, big bit order as numpy packs it).
Arrays are indexed [x, y, z] in the ego frame of the frame's timestamp (see `nuplan_occ.grid`);
`flow` has a trailing axis of 3 (vx, vy, vz) in m/s, ego frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import zstandard

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.errors import DatasetFormatError, InvalidFrameError


@dataclass(frozen=True)
class MemberSpec:
    """One array member: its key in `FrameRecord.arrays`, its tar suffix, dtype and codec."""

    name: str
    suffix: str
    dtype: str
    channels: tuple[int, ...]
    packbits: bool
    default_level: int

    def shape(self, grid: GridSpec) -> tuple[int, ...]:
        """Array shape of this member on `grid`: grid.shape plus trailing channels."""
        return (*grid.shape, *self.channels)

    def describe(self, grid: GridSpec, level: int) -> dict:
        """The member's entry in dataset metadata."""
        encoding = "np.packbits (C order) + zstd" if self.packbits else "dense C-order little-endian + zstd"
        return {
            "suffix": self.suffix,
            "dtype": self.dtype,
            "shape": list(self.shape(grid)),
            "encoding": encoding,
            "zstd_level": level,
        }


MEMBERS: dict[str, MemberSpec] = {
    m.name: m
    for m in (
        MemberSpec("semantics", "sem.zst", "uint8", (), False, 9),
        MemberSpec("mask_lidar", "mask_lidar.bits.zst", "bool", (), True, 3),
        MemberSpec("mask_camera", "mask_camera.bits.zst", "bool", (), True, 3),
        MemberSpec("instance", "inst.zst", "uint16", (), False, 3),
        MemberSpec("flow", "flow.zst", "float16", (3,), False, 3),
    )
}
"""Array members in their fixed manifest-column order."""


def check_array(spec: MemberSpec, array: np.ndarray, grid: GridSpec, where: str) -> None:
    """Raise InvalidFrameError unless `array` has exactly the member's dtype and shape on `grid`."""
    if not isinstance(array, np.ndarray):
        raise InvalidFrameError(f"{where}: member {spec.name!r} is {type(array).__name__}, not a numpy array")
    if array.dtype != np.dtype(spec.dtype):
        raise InvalidFrameError(f"{where}: member {spec.name!r} has dtype {array.dtype}, expected {spec.dtype}")
    if array.shape != spec.shape(grid):
        raise InvalidFrameError(f"{where}: member {spec.name!r} has shape {array.shape}, expected {spec.shape(grid)}")


def encode(spec: MemberSpec, array: np.ndarray, level: int) -> bytes:
    """Compressed member bytes of a checked array (see module docstring for the layout)."""
    if spec.packbits:
        raw = np.packbits(np.ascontiguousarray(array).reshape(-1)).tobytes()
    else:
        raw = np.ascontiguousarray(array, dtype=np.dtype(spec.dtype).newbyteorder("<")).tobytes()
    return zstandard.ZstdCompressor(level=level, write_content_size=True, write_checksum=False).compress(raw)


def _decompress_into(blob: bytes, out: np.ndarray, where: str) -> None:
    """Decompress one zstd frame into the bytes of the preallocated C-contiguous `out`."""
    try:
        size = zstandard.frame_content_size(blob)
    except zstandard.ZstdError as exc:
        raise DatasetFormatError(f"{where}: not a zstd frame ({exc})") from exc
    if size != out.nbytes:
        raise DatasetFormatError(f"{where}: zstd content size {size} != expected {out.nbytes} bytes")
    view = memoryview(out.reshape(-1).view(np.uint8))
    filled = 0
    with zstandard.ZstdDecompressor().stream_reader(blob) as reader:
        while filled < out.nbytes:
            n = reader.readinto(view[filled:])
            if n == 0:
                raise DatasetFormatError(f"{where}: zstd stream ended after {filled} of {out.nbytes} bytes")
            filled += n


def decode(spec: MemberSpec, blob: bytes, grid: GridSpec, where: str) -> np.ndarray:
    """Array (writable, native byte order) of a member's compressed bytes; `where` names it in errors."""
    shape = spec.shape(grid)
    n = int(np.prod(shape))
    if spec.packbits:
        packed = np.empty((n + 7) // 8, dtype=np.uint8)
        _decompress_into(blob, packed, where)
        return np.unpackbits(packed, count=n).view(np.bool_).reshape(shape)
    out = np.empty(shape, dtype=np.dtype(spec.dtype).newbyteorder("<"))
    _decompress_into(blob, out, where)
    return out if out.dtype.isnative else out.astype(np.dtype(spec.dtype))
