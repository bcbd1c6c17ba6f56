"""Synthetic occupancy scenes for tests and the bench (not nuPlan data), pure numpy.

Frame content on a grid [x, y, z] (ego frame): a ground layer at z = 0 m (z index of 0 m, clipped into the
grid): a road band along x with road_line rows at its edges and centre, other_ground elsewhere; a few
vehicle boxes (4.5 x 2 x 1.5 m) on the road, moving along +x by `speed` m/s per 0.1 s frame.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE, VEHICLE

FRAME_PERIOD_S = 0.1


def synthetic_scene(grid: GridSpec, frames: int, rng: np.random.Generator, vehicles: int = 3,
                    speed: float = 5.0) -> np.ndarray:
    """uint8 [frames, X, Y, Z] of one scene with random road placement and vehicle positions."""
    nx, ny, nz = grid.shape
    s = grid.voxel_size
    k = int(np.clip(np.floor(-grid.z_min / s), 0, nz - 1))
    width = int(rng.integers(ny // 4, ny // 2))
    j0 = int(rng.integers(0, ny - width))
    ground = np.full((nx, ny), OTHER_GROUND, dtype=np.uint8)
    ground[:, j0:j0 + width] = ROAD
    line_rows = [j0, j0 + width // 2, j0 + width - 1]
    dashes = (np.arange(nx) // max(int(round(3.0 / s)), 1)) % 2 == 0
    ground[:, line_rows[0]] = ROAD_LINE
    ground[:, line_rows[2]] = ROAD_LINE
    ground[dashes, line_rows[1]] = ROAD_LINE
    size = np.maximum(np.round(np.array([4.5, 2.0, 1.5]) / s).astype(int), 1)
    starts_x = rng.uniform(0, nx, vehicles)
    lanes_y = rng.integers(j0, max(j0 + width - size[1], j0 + 1), vehicles)
    out = np.zeros((frames, nx, ny, nz), dtype=np.uint8)
    for t in range(frames):
        out[t, :, :, k] = ground
        for x0, y0 in zip(starts_x, lanes_y):
            xi = int(x0 + t * speed * FRAME_PERIOD_S / s) % nx
            xs = np.arange(xi, xi + size[0]) % nx
            out[t, xs[:, None], np.arange(y0, min(y0 + size[1], ny))[None], k + 1:k + 1 + size[2]] = VEHICLE
    return out
