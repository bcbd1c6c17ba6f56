"""Member codecs: how each per-frame array is turned into the bytes of one tar member and back.

A member is a payload compressed as one standard stream; the payload is one of two layouts:
- "dense": the C-order array bytes, little-endian (x slowest, then y, z, then any channel fastest);
- "packbits": bool arrays as `np.packbits` of the C-order flattened array (first voxel in the most
  significant bit of byte 0, last byte zero-padded): ceil(n / 8) bytes for n voxels.
The container is a zstd frame with its content size in the header, or an .xz stream (LZMA2, CRC32
check). Both are read by stock tools (`zstd -d`, `xz -d`, Python's zstandard / lzma). The masks use xz at
preset 0 (LZMA2's fast mode): its range coder suits packed bits better than zstd at equal encode time, and
preset 6 saves a fifth of the mask bytes for ten times the encode time (sizes and times: the notes of
bench/report-scale.md). A decoder recognises the container by its magic bytes, so datasets of schema
version 1 (zstd masks) and masks of any preset stay readable.
Arrays are indexed [x, y, z] in the ego frame of the frame's timestamp (see `nuplan_occ.grid`);
`flow` has a trailing axis of 3 (vx, vy, vz) in m/s, ego frame.
"""

from __future__ import annotations

import lzma
from dataclasses import dataclass

import numpy as np
import zstandard

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.errors import DatasetFormatError, InvalidFrameError

ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
XZ_MAGIC = b"\xfd7zXZ\x00"
LEVEL_RANGE = {"zstd": (-7, 22), "xz": (0, 9)}
"""Valid levels per container: zstd level, xz preset."""
XZ_LITERAL_CONTEXT = {"lc": 0, "lp": 2, "pb": 2}
"""LZMA2 literal/position context bits: for packed masks on a 32-voxel z axis, the byte position mod 4
(lp = pb = 2) is which 8 z-voxels of a column a byte holds; the previous byte's bits add nothing (lc = 0)."""
XZ_MEMLIMIT = 1 << 28
"""Largest decoder memory (bytes) an xz member may ask for; corrupt headers fail fast instead of allocating."""


@dataclass(frozen=True)
class MemberSpec:
    """One array member: its key in `FrameRecord.arrays`, tar suffix, dtype, payload layout and container."""

    name: str
    suffix: str
    dtype: str
    channels: tuple[int, ...]
    packbits: bool
    container: str
    default_level: int

    def shape(self, grid: GridSpec) -> tuple[int, ...]:
        """Array shape of this member on `grid`: grid.shape plus trailing channels."""
        return (*grid.shape, *self.channels)

    def payload_nbytes(self, grid: GridSpec) -> int:
        """Size of the decompressed payload on `grid`."""
        n = int(np.prod(self.shape(grid)))
        return (n + 7) // 8 if self.packbits else n * np.dtype(self.dtype).itemsize

    def encoding(self, grid: GridSpec) -> str:
        """Exact decoding instructions: enough to write a reader from this text alone."""
        shape = "x".join(map(str, self.shape(grid)))
        if self.packbits:
            layout = (f"bool {shape}: np.packbits of the array flattened in C order (x slowest, z fastest; "
                      "first voxel in the most significant bit of byte 0; last byte zero-padded)")
        else:
            layout = (f"{self.dtype} {shape}: dense C-order bytes, little-endian "
                      "(x slowest, then y, z, then any trailing channel fastest)")
        if self.container == "xz":
            stream = "one .xz stream (LZMA2 filter, CRC32 check); decode with any xz decoder, e.g. Python lzma.decompress"
        else:
            stream = "one zstd frame with the content size in its header; decode with any zstd decoder"
        return f"{layout}; {self.payload_nbytes(grid)} payload bytes compressed as {stream}"

    def describe(self, grid: GridSpec, level: int) -> dict:
        """The member's entry in dataset metadata."""
        return {
            "suffix": self.suffix,
            "dtype": self.dtype,
            "shape": list(self.shape(grid)),
            "encoding": self.encoding(grid),
            "container": self.container,
            "level": level,
        }


MEMBERS: dict[str, MemberSpec] = {
    m.name: m
    for m in (
        MemberSpec("semantics", "sem.zst", "uint8", (), False, "zstd", 9),
        MemberSpec("mask_lidar", "mask_lidar.bits.xz", "bool", (), True, "xz", 0),
        MemberSpec("mask_camera", "mask_camera.bits.xz", "bool", (), True, "xz", 0),
        MemberSpec("instance", "inst.zst", "uint16", (), False, "zstd", 3),
        MemberSpec("flow", "flow.zst", "float16", (3,), False, "zstd", 3),
    )
}
"""Array members in their fixed manifest-column order; levels are zstd levels or xz presets. instance and
flow are almost all zeros, so level 3 rather than 9 costs them little size and saves most of their encode
time (measured in the notes of bench/report-scale.md)."""


def check_array(spec: MemberSpec, array: np.ndarray, grid: GridSpec, where: str) -> None:
    """Raise InvalidFrameError unless `array` has exactly the member's dtype and shape on `grid`."""
    if not isinstance(array, np.ndarray):
        raise InvalidFrameError(f"{where}: member {spec.name!r} is {type(array).__name__}, not a numpy array")
    if array.dtype != np.dtype(spec.dtype):
        raise InvalidFrameError(f"{where}: member {spec.name!r} has dtype {array.dtype}, expected {spec.dtype}")
    if array.shape != spec.shape(grid):
        raise InvalidFrameError(f"{where}: member {spec.name!r} has shape {array.shape}, expected {spec.shape(grid)}")


def _xz_filters(level: int, nbytes: int) -> list[dict]:
    """LZMA2 at preset `level`, dictionary no larger than the payload needs (bounds decoder memory)."""
    dict_size = 1 << max(12, int(nbytes - 1).bit_length())
    return [{"id": lzma.FILTER_LZMA2, "preset": level, "dict_size": dict_size, **XZ_LITERAL_CONTEXT}]


def encode(spec: MemberSpec, array: np.ndarray, level: int) -> bytes:
    """Compressed member bytes of a checked array (see module docstring for the layout)."""
    low, high = LEVEL_RANGE[spec.container]
    if not low <= level <= high:
        raise InvalidFrameError(f"member {spec.name!r}: level {level} outside {spec.container} range [{low}, {high}]")
    if spec.packbits:
        payload = np.packbits(np.ascontiguousarray(array).reshape(-1))
    else:
        payload = np.ascontiguousarray(array, dtype=np.dtype(spec.dtype).newbyteorder("<"))
    raw = memoryview(payload.reshape(-1).view(np.uint8))  # the array's own bytes: no copy of the payload
    if spec.container == "xz":
        return lzma.compress(raw, format=lzma.FORMAT_XZ, check=lzma.CHECK_CRC32, filters=_xz_filters(level, len(raw)))
    return _zstd_frame(raw, level)


def _zstd_frame(raw: memoryview, level: int) -> bytes:
    """One zstd frame of `raw` with its content size, produced through the streaming API in small output
    chunks: the one-shot API allocates a compress-bound output (the payload's size) per member and shrinks
    it in place, which left the heap fragmented by ~5 MB per member and frame (scale-report notes)."""
    compressor = zstandard.ZstdCompressor(level=level, write_content_size=True, write_checksum=False)
    stream = compressor.compressobj(size=len(raw))
    return stream.compress(raw) + stream.flush()


def _zstd_into(blob: bytes, out: np.ndarray, where: str) -> None:
    """Decompress one zstd frame into the bytes of the preallocated C-contiguous `out`."""
    try:
        size = zstandard.frame_content_size(blob)
    except zstandard.ZstdError as exc:
        raise DatasetFormatError(f"{where}: not a zstd frame ({exc})") from exc
    if size != out.nbytes:
        raise DatasetFormatError(f"{where}: zstd content size {size} != expected {out.nbytes} bytes")
    view = memoryview(out.reshape(-1).view(np.uint8))
    filled = 0
    try:
        with zstandard.ZstdDecompressor().stream_reader(blob) as reader:
            while filled < out.nbytes:
                n = reader.readinto(view[filled:])
                if n == 0:
                    raise DatasetFormatError(f"{where}: zstd stream ended after {filled} of {out.nbytes} bytes")
                filled += n
    except zstandard.ZstdError as exc:
        raise DatasetFormatError(f"{where}: corrupt zstd frame ({exc})") from exc


def _xz_into(blob: bytes, out: np.ndarray, where: str) -> None:
    """Decompress one complete .xz stream (nothing after it) into the bytes of `out`."""
    decompressor = lzma.LZMADecompressor(format=lzma.FORMAT_XZ, memlimit=XZ_MEMLIMIT)
    try:
        data = decompressor.decompress(blob, max_length=out.nbytes + 1)
    except lzma.LZMAError as exc:
        raise DatasetFormatError(f"{where}: corrupt xz stream ({exc})") from exc
    if len(data) != out.nbytes:
        raise DatasetFormatError(f"{where}: xz payload has {len(data)}+ bytes, expected {out.nbytes}")
    if not decompressor.eof or decompressor.unused_data:
        raise DatasetFormatError(f"{where}: xz stream truncated or followed by extra bytes")
    out.reshape(-1).view(np.uint8)[:] = np.frombuffer(data, dtype=np.uint8)


def _decompress_into(blob: bytes, out: np.ndarray, where: str) -> None:
    """Fill `out` from a zstd frame or an xz stream, told apart by their magic bytes."""
    if blob[:4] == ZSTD_MAGIC:
        _zstd_into(blob, out, where)
    elif blob[:6] == XZ_MAGIC:
        _xz_into(blob, out, where)
    else:
        raise DatasetFormatError(f"{where}: neither a zstd frame nor an xz stream (starts {bytes(blob[:6])!r})")


def decode(spec: MemberSpec, blob: bytes, grid: GridSpec, where: str) -> np.ndarray:
    """Array (writable, native byte order) of a member's compressed bytes; `where` names it in errors."""
    shape = spec.shape(grid)
    if spec.packbits:
        packed = np.empty(spec.payload_nbytes(grid), dtype=np.uint8)
        _decompress_into(blob, packed, where)
        return np.unpackbits(packed, count=int(np.prod(shape))).view(np.bool_).reshape(shape)
    out = np.empty(shape, dtype=np.dtype(spec.dtype).newbyteorder("<"))
    _decompress_into(blob, out, where)
    return out if out.dtype.isnative else out.astype(np.dtype(spec.dtype))
