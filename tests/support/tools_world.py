"""Small synthetic frames and datasets for the dataset-tool tests (ego frame, [x, y, z] indexing)."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import BARRIER, OTHER, OTHER_GROUND, PEDESTRIAN, ROAD, ROAD_LINE, VEHICLE


def _box(grid: GridSpec, lo_m, hi_m) -> tuple[slice, slice, slice]:
    """Index slices of the voxels whose centres lie in the ego-frame box [lo_m, hi_m) (metres)."""
    lo = np.ceil((np.asarray(lo_m) - grid.lower) / grid.voxel_size - 0.5).astype(int)
    hi = np.ceil((np.asarray(hi_m) - grid.lower) / grid.voxel_size - 0.5).astype(int)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))  # type: ignore[return-value]


def street_scene(shift_m: float = 0.0, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """A street: road (|y| < 7 m) with a centre line, walkways, walls, two cars, a pedestrian, a barrier.

    Ground top at z = -0.25 m... 0 m (one voxel layer below the rear axle's z = 0). shift_m moves the
    objects along x. Returns (X, Y, Z) uint8 label ids.
    """
    sem = np.zeros(grid.shape, dtype=np.uint8)
    sem[_box(grid, (-50, -50, -0.25), (50, 50, 0.0))] = OTHER_GROUND
    sem[_box(grid, (-50, -7, -0.25), (50, 7, 0.0))] = ROAD
    sem[_box(grid, (-50, -0.25, -0.25), (50, 0.25, 0.0))] = ROAD_LINE
    sem[_box(grid, (-50, 12, 0), (50, 12.5, 4))] = OTHER
    sem[_box(grid, (-50, -12.5, 0), (50, -12, 4))] = OTHER
    sem[_box(grid, (8 + shift_m, 1.5, 0), (12.5 + shift_m, 3.5, 1.5))] = VEHICLE
    sem[_box(grid, (-15 + shift_m, -4, 0), (-10.5 + shift_m, -2, 1.6))] = VEHICLE
    sem[_box(grid, (5, 8, 0), (5.5, 8.5, 1.75))] = PEDESTRIAN
    sem[_box(grid, (20, -8, 0), (30, -7.5, 1))] = BARRIER
    return sem


SMALL = GridSpec(x_min=-4.0, x_max=4.0, y_min=-4.0, y_max=4.0, z_min=-1.0, z_max=1.0, voxel_size=0.25)
"""32 x 32 x 8 voxels: small enough for fast dataset tests."""

LOG = "2021.05.12.22.00.38_veh-35_01008_01518"


def small_scene(seed: int, grid: GridSpec = SMALL) -> np.ndarray:
    """A random small frame: road ground layer at z index 2, random vehicle/pedestrian/other voxels above."""
    rng = np.random.default_rng(seed)
    sem = np.zeros(grid.shape, dtype=np.uint8)
    sem[:, :, 2] = ROAD
    sem[:, : grid.shape[1] // 4, 2] = OTHER_GROUND
    upper = sem[:, :, 3:]
    upper[rng.random(upper.shape) < 0.05] = VEHICLE
    upper[rng.random(upper.shape) < 0.02] = PEDESTRIAN
    upper[rng.random(upper.shape) < 0.02] = OTHER
    return sem


def token_of(i: int) -> str:
    """A 16-hex-digit token for frame i."""
    return f"{i:016x}"


def write_dataset(root, frames: list[dict], grid: GridSpec = SMALL, failed: dict[int, str] | None = None,
                  columns: dict[int, dict] | None = None) -> None:
    """Write a one-log dataset: frames[i] = arrays of frame index i (token `token_of(i)`); `failed` maps
    further frame indices to failure reasons; `columns` extra manifest columns per frame index."""
    from nuplan_occ.storage import DatasetWriter, FrameRecord

    def record(i: int, arrays: dict, status: str = "ok", reason: str = "") -> FrameRecord:
        pose = np.eye(4)
        pose[0, 3] = 1000.0 + i
        return FrameRecord(log=LOG, log_id=0, scene_token="ab" * 8, scene_name="scene-0000", frame_index=i,
                           token=token_of(i), timestamp_us=1_000_000 + 50_000 * i, ego_to_global=pose,
                           arrays=arrays, columns=(columns or {}).get(i, {}), status=status, failure_reason=reason)

    records = [record(i, arrays) for i, arrays in enumerate(frames) if arrays is not None]
    records += [record(i, {}, "failed", reason) for i, reason in (failed or {}).items()]
    writer = DatasetWriter(str(root), metadata={"params": {}}, grid=grid)
    writer.commit(writer.write_shard(f"{LOG}/scene-0000", records))
