"""The merged LiDAR blob format: binary PCD v0.7.

Points are returned in the "lidar" frame, the frame of the DB's `MergedPointCloud` lidar row (metres).
The record layout is built from the header's FIELDS / SIZE / TYPE (little-endian, packed); only
`DATA binary` is accepted, every COUNT must be 1, and bytes after the last record are ignored (the devkit
notes trailing garbage in real files). Every malformed input raises PointCloudError.

`read_pcd` decodes what the file holds; `usable_points` is the gate a sweep passes before the pipeline uses
it (the reader applies it in `NuplanLog.load_sweep`): points that no LiDAR can have measured are dropped and
counted, and a sweep that is empty or mostly such points fails.
"""

from __future__ import annotations

import numpy as np

from dataclasses import dataclass

from nuplan_occ.io.errors import PointCloudError
from nuplan_occ.io.types import PointCloud

MAX_HEADER_BYTES = 64 * 1024
"""The header (everything up to and including the DATA line) must fit in this many bytes."""

MAX_POINTS = 4_000_000
"""A PCD may hold at most this many points (~100 MB decoded): merged nuPlan sweeps hold a few hundred thousand,
so a larger POINTS is a damaged header, refused before anything is allocated."""

MAX_RANGE_M = 250.0
"""Points farther than this from the merged LiDAR frame's origin are dropped: the longest-range LiDAR of the
nuPlan car measures to about 200 m and the others sit within a few metres of that origin, so nothing farther
is a return. The grid itself only spans 71 m of horizontal range (its corners)."""

MIN_USABLE_FRACTION = 0.5
"""A sweep fails when fewer than this fraction of its points are usable: a few bad returns are noise, more is a
broken sensor or file."""

_KINDS = {"F": "f", "I": "i", "U": "u"}
_SIZES = {1, 2, 4, 8}
_REQUIRED_KEYS = ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA")
_OPTIONAL = ("intensity", "ring", "lidar_info")


def _parse_header(buf: bytes, source: str) -> tuple[dict[str, list[str]], int]:
    """Header keys (upper-cased) -> values, and the byte offset where the point records start.

    Reads lines up to the DATA line, never past MAX_HEADER_BYTES.
    """
    header: dict[str, list[str]] = {}
    pos = 0
    while "DATA" not in header:
        newline = buf.find(b"\n", pos, MAX_HEADER_BYTES)
        if newline < 0:
            raise PointCloudError(source, f"no DATA line within the first {MAX_HEADER_BYTES} bytes "
                                          "(truncated header or not a PCD file)")
        try:
            line = buf[pos:newline].decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointCloudError(source, f"PCD header line at byte {pos} is not ASCII") from None
        pos = newline + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        key = key.upper()
        if key in header:
            raise PointCloudError(source, f"PCD header repeats the key {key}")
        header[key] = values
    missing = [key for key in _REQUIRED_KEYS if key not in header]
    if missing:
        raise PointCloudError(source, f"PCD header lacks {', '.join(missing)}")
    return header, pos


def _record_dtype(header: dict[str, list[str]], source: str) -> np.dtype:
    """Packed little-endian record dtype from FIELDS / SIZE / TYPE (/ COUNT, which must be all 1)."""
    fields, sizes, kinds = header["FIELDS"], header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    if not fields or not (len(fields) == len(sizes) == len(kinds) == len(counts)):
        raise PointCloudError(
            source, f"PCD header lists {len(fields)} FIELDS, {len(sizes)} SIZE, {len(kinds)} TYPE, {len(counts)} COUNT"
        )
    if len(set(fields)) != len(fields):
        raise PointCloudError(source, f"PCD FIELDS repeat a name: {' '.join(fields)}")
    if any(count != "1" for count in counts):
        raise PointCloudError(source, f"unsupported PCD COUNT {' '.join(counts)} (every COUNT must be 1)")
    columns = []
    for name, size, kind in zip(fields, sizes, kinds):
        if kind.upper() not in _KINDS or not size.isdigit() or int(size) not in _SIZES:
            raise PointCloudError(source, f"unsupported PCD field {name}: TYPE {kind} SIZE {size}")
        if kind.upper() == "F" and int(size) == 1:
            raise PointCloudError(source, f"unsupported PCD field {name}: 1-byte float")
        columns.append((name, f"<{_KINDS[kind.upper()]}{size}"))
    missing_xyz = [axis for axis in "xyz" if axis not in fields]
    if missing_xyz:
        raise PointCloudError(source, f"PCD FIELDS lack {', '.join(missing_xyz)}")
    return np.dtype(columns)


def _point_count(header: dict[str, list[str]], source: str) -> int:
    values = header["POINTS"]
    if len(values) != 1 or not values[0].isdigit():
        raise PointCloudError(source, f"bad PCD POINTS {' '.join(values)}")
    return int(values[0])


def _int_column(values: np.ndarray, lo: int, hi: int, dtype: type) -> np.ndarray:
    """Integer column; values that are not finite integers within [lo, hi] become -1."""
    as_float = values.astype(np.float64)
    ok = np.isfinite(as_float) & (as_float >= lo) & (as_float <= hi)
    out = np.full(len(values), -1, dtype=dtype)
    out[ok] = as_float[ok].astype(dtype)
    return out


def read_pcd(buf: bytes, source: str) -> PointCloud:
    """Parse a binary PCD blob; source names the file in errors.

    Returns a PointCloud in the "lidar" frame: xyz float64 m, intensity float32, ring int16, lidar_info int8
    (0..4, see LIDAR_NAMES). Fields absent from the file, and ring / lidar_info values that are out of range
    or not finite, are -1.
    """
    if not isinstance(buf, (bytes, bytearray, memoryview)):
        raise PointCloudError(source, f"expected bytes, got {type(buf).__name__}")
    buf = bytes(buf)
    header, offset = _parse_header(buf, source)
    data = header["DATA"]
    if len(data) != 1 or data[0].lower() != "binary":
        raise PointCloudError(source, f"unsupported PCD DATA {' '.join(data) or '(empty)'} (only 'binary')")
    dtype = _record_dtype(header, source)
    n = _point_count(header, source)
    if n > MAX_POINTS:
        raise PointCloudError(source, f"PCD POINTS {n} exceeds the {MAX_POINTS} points a sweep may hold")
    needed = n * dtype.itemsize
    if len(buf) - offset < needed:
        raise PointCloudError(
            source, f"truncated PCD: {n} points need {needed} bytes of data, file has {len(buf) - offset}"
        )
    records = np.frombuffer(buf, dtype=dtype, count=n, offset=offset)
    with np.errstate(over="ignore", invalid="ignore"):
        xyz = np.empty((n, 3))
        for column, axis in enumerate("xyz"):  # each field straight into its column: no per-axis temporaries
            xyz[:, column] = records[axis]
        names = records.dtype.names
        intensity = (records["intensity"].astype(np.float32) if "intensity" in names
                     else np.full(n, -1, dtype=np.float32))
        ring = _int_column(records["ring"], 0, np.iinfo(np.int16).max, np.int16) if "ring" in names \
            else np.full(n, -1, dtype=np.int16)
        lidar_info = _int_column(records["lidar_info"], 0, 4, np.int8) if "lidar_info" in names \
            else np.full(n, -1, dtype=np.int8)
    return PointCloud(xyz=xyz, intensity=intensity, ring=ring, lidar_info=lidar_info, frame="lidar")


@dataclass(frozen=True)
class DroppedPoints:
    """Points of a sweep that `usable_points` dropped: non-finite coordinates, farther than MAX_RANGE_M, or
    exactly at the origin (the null return some drivers write for a ray without an echo)."""

    non_finite: int = 0
    too_far: int = 0
    at_origin: int = 0

    @property
    def total(self) -> int:
        return self.non_finite + self.too_far + self.at_origin

    def __str__(self) -> str:
        return (f"{self.non_finite} non-finite, {self.too_far} beyond {MAX_RANGE_M:g} m, "
                f"{self.at_origin} at the sensor origin")


def usable_points(cloud: PointCloud, source: str) -> tuple[PointCloud, DroppedPoints]:
    """The points of a "lidar"-frame sweep a LiDAR can have measured, and what was dropped (see DroppedPoints).

    PointCloudError (naming `source`) when the sweep holds no point or fewer than MIN_USABLE_FRACTION of its
    points are usable.
    """
    n = len(cloud)
    if n == 0:
        raise PointCloudError(source, "PCD holds no points")
    xyz = cloud.xyz
    finite = np.isfinite(xyz).all(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        squared = np.einsum("ij,ij->i", xyz, xyz)
    near = finite & (squared <= MAX_RANGE_M ** 2)
    keep = near & (squared > 0.0)
    dropped = DroppedPoints(non_finite=int(n - finite.sum()), too_far=int(finite.sum() - near.sum()),
                            at_origin=int(near.sum() - keep.sum()))
    usable = n - dropped.total
    if usable < MIN_USABLE_FRACTION * n:
        raise PointCloudError(source, f"only {usable} of the PCD's {n} points are usable ({dropped})")
    return (cloud if usable == n else cloud.subset(keep)), dropped


def encode_pcd(cloud: PointCloud) -> bytes:
    """The devkit-compatible binary PCD of a cloud in the "lidar" frame (all six fields float32).

    Header as nuPlan's MergedPointCloud blobs carry it; records x y z intensity ring lidar_info.
    """
    if cloud.frame != "lidar":
        raise ValueError(f"encode_pcd expects points in the 'lidar' frame, got {cloud.frame!r}")
    n = len(cloud)
    records = np.empty((n, 6), dtype="<f4")
    records[:, :3] = cloud.xyz
    records[:, 3] = cloud.intensity
    records[:, 4] = cloud.ring
    records[:, 5] = cloud.lidar_info
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        "FIELDS x y z intensity ring lidar_info\n"
        "SIZE 4 4 4 4 4 4\n"
        "TYPE F F F F F F\n"
        "COUNT 1 1 1 1 1 1\n"
        f"WIDTH {n}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {n}\n"
        "DATA binary\n"
    )
    return header.encode("ascii") + records.tobytes()
