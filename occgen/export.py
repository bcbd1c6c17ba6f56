"""Writing generated (or synthetic) occupancy as a dataset that `nuplan-occ view` opens.

This is occgen's one use of `nuplan_occ.storage` (the dataset writer). Generated grids are smaller or
larger than the dataset grid: `place_in_grid` puts a grid whose lower corner is at `lower_m` (metres, in
the output frame's ego frame) into the output grid by metric position, padding with empty (0) and
cropping what falls outside. `canvas_windows` cuts a large canvas into output-grid windows, each a
frame whose ego frame is the canvas frame translated to the window.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.storage import DatasetWriter, FrameRecord

FRAME_PERIOD_US = 100_000


@dataclass
class GeneratedScene:
    """frames: uint8 [T, X, Y, Z] on the output grid; ego_to_global: [T, 4, 4] (T_global_from_ego)."""

    name: str
    frames: np.ndarray
    ego_to_global: np.ndarray
    columns: dict = field(default_factory=dict)


def place_in_grid(sem: np.ndarray, lower_m: np.ndarray, voxel_size: float, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """uint8 grid.shape holding `sem` [X, Y, Z] whose voxel (0, 0, 0) has its lower corner at `lower_m`."""
    if not np.isclose(voxel_size, grid.voxel_size):
        raise ValueError(f"voxel size {voxel_size} m differs from the output grid's {grid.voxel_size} m")
    offset = np.round((np.asarray(lower_m, dtype=np.float64) - grid.lower) / grid.voxel_size).astype(int)
    out = np.zeros(grid.shape, dtype=np.uint8)
    src, dst = [], []
    for axis in range(3):
        lo = max(offset[axis], 0)
        hi = min(offset[axis] + sem.shape[axis], grid.shape[axis])
        if hi <= lo:
            return out
        dst.append(slice(lo, hi))
        src.append(slice(lo - offset[axis], hi - offset[axis]))
    out[tuple(dst)] = sem[tuple(src)]
    return out


def translation(offset_m: np.ndarray) -> np.ndarray:
    """4 x 4 pose translating by `offset_m` (3,) metres."""
    pose = np.eye(4)
    pose[:3, 3] = offset_m
    return pose


def canvas_windows(canvas: np.ndarray, lower_m: np.ndarray, voxel_size: float,
                   grid: GridSpec = DEFAULT_GRID) -> list[tuple[np.ndarray, np.ndarray]]:
    """(frame uint8 grid.shape, T_canvas_from_window_ego) for the grid-sized windows covering the canvas.

    canvas [X, Y, Z] with its lower corner at `lower_m` (metres, canvas frame). Window (a, b) is the
    output grid translated by (a * extent_x, b * extent_y) metres in x and y.
    """
    extent = grid.upper - grid.lower
    first = np.floor((lower_m[:2] - grid.lower[:2]) / extent[:2]).astype(int)
    last = np.floor((lower_m[:2] + np.array(canvas.shape[:2]) * voxel_size - 1e-9 - grid.lower[:2]) / extent[:2])
    out = []
    for a in range(first[0], int(last[0]) + 1):
        for b in range(first[1], int(last[1]) + 1):
            shift = np.array([a * extent[0], b * extent[1], 0.0])
            out.append((place_in_grid(canvas, lower_m - shift, voxel_size, grid), translation(shift)))
    return out


def _hex(text: str) -> str:
    return hashlib.sha1(text.encode()).hexdigest()[:32]


def write_scenes(root: str, scenes: list[GeneratedScene], params: dict, grid: GridSpec = DEFAULT_GRID,
                 zstd_level: int | None = None) -> int:
    """Write each scene as one log (one shard) under `root` and commit; returns the frame count."""
    levels = {"semantics": zstd_level} if zstd_level is not None else None
    writer = DatasetWriter(root, metadata={"params": params}, grid=grid, zstd_levels=levels)
    rows = []
    for log_id, scene in enumerate(scenes):
        if scene.frames.shape[1:] != grid.shape:
            raise ValueError(f"scene {scene.name}: frames {scene.frames.shape[1:]} are not on the grid {grid.shape}")
        log = f"occgen-{scene.name}"
        records = [
            FrameRecord(log=log, log_id=log_id, scene_token=_hex(log), scene_name=scene.name, frame_index=t,
                        token=_hex(f"{log}/{t}"), timestamp_us=t * FRAME_PERIOD_US,
                        ego_to_global=scene.ego_to_global[t], arrays={"semantics": scene.frames[t]},
                        columns=dict(scene.columns))
            for t in range(len(scene.frames))
        ]
        rows += writer.write_shard(f"{log}/scene-0000", records)
    writer.commit(rows)
    return len(rows)
