"""Points below the ground (multipath ghosts: a ground return seen again further along its ray, under the road).

The ground of a point is a lower envelope of the cloud: in x-y cells of `cell_m`, a low percentile of the
heights of the cell's points (a cell needs `min_cell_points`), then the lowest of those over the
(2 * reach + 1)^2 cells around (so a cell of wall or vehicle points takes the ground of the road beside it).
Ghosts are a small share of the returns, so they do not move the percentile. Frame: any frame with z up
(the ego or scene frame); metres.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def ground_envelope(points: np.ndarray, cell_m: float = 1.0, percentile: float = 10.0, min_cell_points: int = 5,
                    reach: int = 2) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(ground (I, J) m, NaN where no cell within reach has enough points; cell index (N, 2) of each point;
    x0, y0: the lower corner of cell (0, 0)) of points (N, 3)."""
    xyz = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(xyz):
        return np.full((0, 0), np.nan), np.zeros((0, 2), np.int64), 0.0, 0.0
    x0, y0 = float(xyz[:, 0].min()), float(xyz[:, 1].min())
    cell = np.floor((xyz[:, :2] - [x0, y0]) / cell_m).astype(np.int64)
    shape = tuple(cell.max(axis=0) + 1)
    flat = cell[:, 0] * shape[1] + cell[:, 1]
    order = np.lexsort((xyz[:, 2], flat))
    counts = np.bincount(flat, minlength=shape[0] * shape[1])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.floor(percentile / 100.0 * np.maximum(counts - 1, 0)).astype(np.int64)
    low = np.full(shape[0] * shape[1], np.inf)
    enough = counts >= min_cell_points
    low[enough] = xyz[order[starts[enough] + rank[enough]], 2]
    ground = ndimage.minimum_filter(low.reshape(shape), size=2 * reach + 1, mode="constant", cval=np.inf)
    return np.where(np.isfinite(ground), ground, np.nan), cell, x0, y0


def below_ground(points: np.ndarray, depth_m: float = 0.5, cell_m: float = 1.0, percentile: float = 10.0,
                 min_cell_points: int = 5, reach: int = 2) -> np.ndarray:
    """(N,) bool: points (N, 3) lower than depth_m under their ground (`ground_envelope`); False where the
    ground is unknown."""
    ground, cell, _, _ = ground_envelope(points, cell_m, percentile, min_cell_points, reach)
    if not len(cell):
        return np.zeros(0, dtype=bool)
    under = ground[cell[:, 0], cell[:, 1]] - depth_m
    return np.asarray(points)[:, 2] < np.where(np.isnan(under), -np.inf, under)
