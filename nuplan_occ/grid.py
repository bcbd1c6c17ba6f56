"""The occupancy grid convention, one definition for the whole project.

Frame: the ego frame of the frame's timestamp = nuPlan rear axle, x forward, y left, z up (metres).
Arrays are indexed [x, y, z]. Voxel (i, j, k) covers
    x in [x_min + i*s, x_min + (i+1)*s), y likewise, z likewise, with s = voxel_size.
Default: x, y in [-50, 50) m, z in [-3, 5) m, s = 0.25 m, shape 400 x 400 x 32.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class GridSpec:
    """Axis-aligned voxel grid in the ego (rear-axle) frame; bounds in metres, half-open."""

    x_min: float = -50.0
    x_max: float = 50.0
    y_min: float = -50.0
    y_max: float = 50.0
    z_min: float = -3.0
    z_max: float = 5.0
    voxel_size: float = 0.25

    @property
    def lower(self) -> np.ndarray:
        """(3,) lower corner [x_min, y_min, z_min] in metres, ego frame."""
        return np.array([self.x_min, self.y_min, self.z_min], dtype=np.float64)

    @property
    def upper(self) -> np.ndarray:
        """(3,) upper corner [x_max, y_max, z_max] in metres, ego frame (exclusive)."""
        return np.array([self.x_max, self.y_max, self.z_max], dtype=np.float64)

    @property
    def reach(self) -> float:
        """Metres from the ego origin to the grid's farthest corner: no point farther away is inside the grid."""
        return float(np.linalg.norm(np.maximum(np.abs(self.lower), np.abs(self.upper))))

    @cached_property
    def shape(self) -> tuple[int, int, int]:
        """Number of voxels along x, y, z (computed once: hot loops ask for it per call)."""
        extent = (self.upper - self.lower) / self.voxel_size
        return tuple(int(round(v)) for v in extent)  # type: ignore[return-value]

    def point_to_index(self, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxel indices of ego-frame points.

        points_ego: (N, 3) metres in the ego frame.
        Returns (indices (N, 3) int64, inside (N,) bool); indices of points outside the grid are
        clipped and must be discarded with `inside`.
        """
        pts = np.asarray(points_ego, dtype=np.float64).reshape(-1, 3)
        idx = np.floor((pts - self.lower) / self.voxel_size).astype(np.int64)
        shape = np.array(self.shape)
        inside = np.all((idx >= 0) & (idx < shape), axis=1)
        return np.clip(idx, 0, shape - 1), inside

    def column_disc(self, reach_m: float) -> np.ndarray:
        """bool (2r + 1, 2r + 1) footprint of the columns within reach_m (x-y, centre to centre, whole voxels r)
        of the middle one."""
        radius = int(np.floor(reach_m / self.voxel_size + 1e-9))
        offsets = np.arange(-radius, radius + 1)
        return np.hypot(*np.meshgrid(offsets, offsets, indexing="ij")) <= radius + 1e-9

    def index_to_center(self, indices: np.ndarray) -> np.ndarray:
        """Centres (N, 3) in metres, ego frame, of voxel indices (N, 3)."""
        return self.lower + (np.asarray(indices, dtype=np.float64) + 0.5) * self.voxel_size

    def voxel_centers(self) -> np.ndarray:
        """All voxel centres as an array of shape (*shape, 3), metres, ego frame."""
        axes = [
            lo + (np.arange(n) + 0.5) * self.voxel_size
            for lo, n in zip(self.lower, self.shape)
        ]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def to_dict(self) -> dict:
        """The convention as stored in dataset metadata."""
        return {
            "frame": "ego (nuPlan rear axle): x forward, y left, z up",
            "axis_order": ["x", "y", "z"],
            "bounds_m": {
                "x": [self.x_min, self.x_max],
                "y": [self.y_min, self.y_max],
                "z": [self.z_min, self.z_max],
            },
            "voxel_size_m": self.voxel_size,
            "shape": list(self.shape),
            "bounds_are_half_open": True,
            **{"spec": asdict(self)},
        }

    @classmethod
    def from_dict(cls, data: dict) -> "GridSpec":
        """Inverse of `to_dict`."""
        return cls(**data["spec"])


DEFAULT_GRID = GridSpec()


def true_indices(mask: np.ndarray) -> np.ndarray:
    """(K, 3) int64: the indices [x, y, z] of the True voxels of a bool (X, Y, Z) grid, in C order (the rows of
    np.argwhere, which walks every axis of the grid and is about 10x slower on a sparse 400 x 400 x 32 grid)."""
    return np.stack(np.unravel_index(np.flatnonzero(mask), mask.shape), axis=1)


def column_runs(first: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voxels of vertical runs, one run per column c: layers first[c] .. first[c] + count[c] - 1 (count >= 0;
    first, count (C,) int). Returns (column (R,), layer (R,)) int64, R = count.sum(): each voxel's column index
    into first / count and its layer, column by column, layers ascending."""
    count = np.asarray(count, np.int64)
    column = np.repeat(np.arange(len(count)), count)
    return column, np.asarray(first, np.int64)[column] + (np.arange(len(column)) - np.repeat(np.cumsum(count) - count, count))
