"""The LiDAR observations of a scene's output frames, one row per frame: each row holds the frame's observed
voxels and its FREE voxels as packed bits (`visibility.lidar_observation_bits`, np.packbits order over the
grid's flat C order), the observed half first; and the free-space clearing that reads them.

Grids are DEFAULT-style [x, y, z] grids in each frame's ego frame; poses are T_global_from_ego (4, 4).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import GridSpec
from nuplan_occ.rays.free_space import clearable_background, free_voxels_in_frames


@dataclass
class RayObservations:
    """The rows of a scene's observation bits: tokens (sweep tokens of the loaded output frames, scene order)."""

    tokens: list[str]

    def row(self, token: str) -> int:
        """The row of the frame with sweep token `token` (KeyError when it has none)."""
        if token not in self.tokens:
            raise KeyError(f"no LiDAR observation for sweep {token}")
        return self.tokens.index(token)


def split_observation_bits(row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(observed bits, FREE bits) of one row of observation bits."""
    return row[:len(row) // 2], row[len(row) // 2:]


def free_space_clear(candidates_grid: np.ndarray, support: np.ndarray, ground_height: np.ndarray, grid: GridSpec,
                     ground_margin_m: float, own_free: np.ndarray, other_frames: tuple[np.ndarray, np.ndarray] | None
                     ) -> np.ndarray:
    """bool grid of a frame's background voxels to clear: voxels of `candidates_grid` (occupied background)
    holding no aggregated background point (`support`, bool grid), at least ground_margin_m above the local
    ground (`ground_height`, m per column), and crossed by a LiDAR ray: the frame's own (own_free: its FREE
    bits) or, with other_frames = (FREE bits of every row (R, n_bytes), T_row_from_ego (R, 4, 4): this frame's
    ego frame into each row's), any output frame's."""
    candidates = clearable_background(candidates_grid, support, ground_height, grid, ground_margin_m)
    if other_frames is None:
        return free_voxels_in_frames(candidates, np.eye(4)[None], own_free[None], grid)
    bits, transforms = other_frames
    return free_voxels_in_frames(candidates, transforms, bits, grid)


def frames_to(poses: np.ndarray, position: int, tokens: Sequence[str], position_of: dict[str, int], own: int
              ) -> np.ndarray:
    """(R, 4, 4) T_row_from_ego: the ego frame of the sweep at `position` into each row's ego frame (tokens: the
    rows' sweep tokens; position_of: sweep token -> position in `poses`; own: that sweep's own row, whose
    transform is the identity)."""
    return np.stack([np.eye(4) if row == own else invert_transform(poses[position_of[other]]) @ poses[position]
                     for row, other in enumerate(tokens)])
