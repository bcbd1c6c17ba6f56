"""A scene's sweep clouds kept on disk instead of in memory, read back one sweep at a time.

A 20 s scene's clouds are about 1.1 GB (400 sweeps of ~135 k points) and every stage from split to the frame
stream reads them, so holding them made a worker's memory grow with scene length (bench/report-scale.md).
They go, uncompressed, into one unnamed temporary file of the scene's work folder: the operating system
removes it when the scene's data is released or the worker dies (even by SIGKILL), so it never outlives the
scene and never enters the stage cache. Reading a sweep back is a copy from the page cache (about a
millisecond for 135 k points), which page-cache memory serves without counting in the worker's RSS.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nuplan_occ.io.types import PointCloud

CLOUD_FIELDS = ("xyz", "intensity", "ring", "lidar_info")
"""The arrays of a PointCloud, in their order in the file."""


@dataclass(frozen=True)
class StoredCloud:
    """One sweep's cloud in a `SpilledClouds` file: where each field starts (bytes), its dtype and shape."""

    store: "SpilledClouds"
    offsets: tuple[int, ...]
    dtypes: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    frame: str

    def __len__(self) -> int:
        return int(self.shapes[0][0])

    def field(self, name: str) -> np.ndarray:
        """One array of the cloud (a fresh copy), e.g. "xyz"."""
        k = CLOUD_FIELDS.index(name)
        return self.store.read_array(self.offsets[k], np.dtype(self.dtypes[k]), self.shapes[k])

    def read(self) -> PointCloud:
        """The whole cloud (fresh arrays)."""
        return PointCloud(*(self.field(name) for name in CLOUD_FIELDS), frame=self.frame)


class SpilledClouds:
    """Append-only store of point clouds in an unnamed temporary file under `folder` (created if needed)."""

    def __init__(self, folder: Path) -> None:
        Path(folder).mkdir(parents=True, exist_ok=True)
        self._file = tempfile.TemporaryFile(dir=folder)
        self._end = 0

    def add(self, cloud: PointCloud) -> StoredCloud:
        """Write the cloud's arrays at the end of the file; its handle."""
        offsets, dtypes, shapes = [], [], []
        for name in CLOUD_FIELDS:
            array = np.ascontiguousarray(getattr(cloud, name))
            offsets.append(self._end)
            dtypes.append(array.dtype.str)
            shapes.append(tuple(array.shape))
            written = os.pwrite(self._file.fileno(), array.reshape(-1).view(np.uint8), self._end) if array.nbytes else 0
            if written != array.nbytes:
                raise OSError(f"spilled clouds: short write ({written} of {array.nbytes} bytes) to {self._file.name}")
            self._end += array.nbytes
        return StoredCloud(self, tuple(offsets), tuple(dtypes), tuple(shapes), cloud.frame)

    def read_array(self, offset: int, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
        """The array of `shape` and `dtype` stored at byte `offset`."""
        array = np.empty(shape, dtype=dtype)
        view = array.reshape(-1).view(np.uint8)
        done = 0
        while done < array.nbytes:
            got = os.preadv(self._file.fileno(), [view[done:]], offset + done)
            if got <= 0:
                raise OSError(f"spilled clouds: file ends at byte {offset + done}, expected {offset + array.nbytes}")
            done += got
        return array
