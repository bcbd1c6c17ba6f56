"""Points below the ground (multipath ghosts: a ground return seen again further along its ray, under the road).

The ground of a point is a lower envelope of the cloud: in x-y cells of `cell_m`, a low percentile of the
heights of the cell's points (a cell needs `min_cell_points`), then the lowest of those over the
(2 * reach + 1)^2 cells around (so a cell of wall or vehicle points takes the ground of the road beside it).
Ghosts are a small share of the returns, so they do not move the percentile of a cell of real ground.

Where the real ground is hidden (behind a building, under a row of parked cars), the few ghosts landing there
still make sparse cells of their own. Points of sparse cells are therefore also tested against the typical
ground around (a median over some 15 m, which a few ghost cells do not move) with a deeper margin, and, with the
sensor origins known, by their ray: it went under the ground it crossed on the way, so a point whose ray, followed
back toward the sensor, runs lower than depth_m under a known ground is a ghost. Dense cells are not tested against
the typical ground: a ramp or a cutting seen by many sweeps keeps its low ground; their ground-like points (near
their cell's low) are tested by ray only (the rays into a real cutting pass over its rim). Ghosts piling up over many
sweeps make dense cells too, and a cell's envelope takes their low ground: a second pass, over the points the first
kept, finds those the first pass's ghosts hid. Frame: any frame with z up (the ego or scene frame);
metres.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy import ndimage


def cell_lows(points: np.ndarray, cell_m: float = 1.0, percentile: float = 10.0, min_cell_points: int = 5
              ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(low (I, J) m: the percentile of the heights of each x-y cell's points, NaN where a cell has fewer than
    min_cell_points; cell index (N, 2) of each point; x0, y0: the lower corner of cell (0, 0)) of points (N, 3)."""
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
    low = np.full(shape[0] * shape[1], np.nan)
    enough = counts >= min_cell_points
    low[enough] = xyz[order[starts[enough] + rank[enough]], 2]
    return low.reshape(shape), cell, x0, y0


def ground_envelope(points: np.ndarray, cell_m: float = 1.0, percentile: float = 10.0, min_cell_points: int = 5,
                    reach: int = 2) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(ground (I, J) m, NaN where no cell within reach has enough points; cell index (N, 2) of each point;
    x0, y0: the lower corner of cell (0, 0)) of points (N, 3): the lowest `cell_lows` within reach cells."""
    low, cell, x0, y0 = cell_lows(points, cell_m, percentile, min_cell_points)
    return _envelope(low, reach), cell, x0, y0


def _envelope(low: np.ndarray, reach: int) -> np.ndarray:
    """(I, J) the lowest of the cell lows (I, J), NaN unknown, within reach cells; NaN where none is known."""
    ground = ndimage.minimum_filter(np.nan_to_num(low, nan=np.inf), size=2 * reach + 1, mode="constant", cval=np.inf)
    return np.where(np.isfinite(ground), ground, np.nan)


def typical_ground(ground: np.ndarray, block: int) -> np.ndarray:
    """(I, J) the typical ground around each cell: the median of the known grounds (ground (I, J) m, NaN unknown,
    e.g. a `ground_envelope`) of its block of block x block cells, then the median of those over the 3 x 3 blocks around (NaN where none is
    known). A median, so a few cells of ghosts do not move it."""
    I, J = ground.shape
    bi, bj = np.nonzero(np.isfinite(ground))
    nbi, nbj = -(-I // block), -(-J // block)
    blocks = np.full((nbi + 2, nbj + 2), np.nan)
    if len(bi):
        key = (bi // block) * nbj + bj // block
        values = ground[bi, bj]
        order = np.lexsort((values, key))
        key, values = key[order], values[order]
        first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        count = np.diff(np.r_[first, len(key)])
        medians = values[first + count // 2]
        blocks[1 + key[first] // nbj, 1 + key[first] % nbj] = medians
    around = np.stack([blocks[1 + di:1 + di + nbi, 1 + dj:1 + dj + nbj] for di in (-1, 0, 1) for dj in (-1, 0, 1)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # blocks with no known cell around: NaN, as meant
        typical = np.nanmedian(around, axis=0)
    return np.repeat(np.repeat(typical, block, axis=0), block, axis=1)[:I, :J]


SPARSE_CELL_FACTOR = 4
"""A cell holding fewer than this many times min_cell_points points is sparse: where the real ground is hidden, a few
ghosts make a ground of their own there, so its points are tested against the typical ground around and by ray."""
SPARSE_DEPTH_M = 1.0
"""A point of a sparse cell this far under the typical ground around is a ghost (dense cells of real ground that
low, a ramp or a cutting, are never tested so)."""
TYPICAL_BLOCK = 5
"""Cells per side of a block of `typical_ground` (its 3 x 3 blocks span 15 cells)."""

RAY_BACK_M = tuple(float(v) for v in np.round(0.5 * np.sqrt(2.0) ** np.arange(13), 2))
"""Horizontal distances (m) back along a point's ray at which its height is compared with the ground: 0.5 to 32 m,
each sqrt(2) times the last (a ray runs deep enough under known ground over an interval of its length; steps of
sqrt(2) miss only intervals shorter than that ratio)."""


GROUND_LIKE_M = 1.0
"""Points at most this high above their cell's low percentile are ground-like (the road, a kerb, a pile of ghosts) and
ray-tested; a wall's or a car's points above are not."""

PASSES = 2
"""Passes of `below_ground`: a cluster of ghosts is its own low ground, and hides the ghosts beside it until the
first pass has taken its edge."""


def _ground_at(ground: np.ndarray, xy: np.ndarray, x0: float, y0: float, cell_m: float) -> np.ndarray:
    """(N,) the envelope's ground at x-y positions (N, 2), NaN outside it or where unknown."""
    cell = np.floor((xy - [x0, y0]) / cell_m).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < ground.shape), axis=1)
    out = np.full(len(xy), np.nan)
    out[inside] = ground[cell[inside, 0], cell[inside, 1]]
    return out


def below_ground(points: np.ndarray, depth_m: float = 0.5, cell_m: float = 1.0, percentile: float = 10.0,
                 min_cell_points: int = 5, reach: int = 2, origins: np.ndarray | None = None, sparse_depth_m: float = SPARSE_DEPTH_M, block: int = TYPICAL_BLOCK,
                 ray_back_m: tuple[float, ...] = RAY_BACK_M, passes: int = PASSES, chunk: int = 250_000) -> np.ndarray:
    """(N,) bool: ghosts among points (N, 3), found in `passes` passes, each over the points the earlier ones kept
    (`_ghost_pass`): lower than depth_m under their ground (`ground_envelope`, or the `typical_ground` around where
    that is lower: a cell of wall whose foot was hidden does not hold the ground up); or, in a sparse cell (fewer
    than SPARSE_CELL_FACTOR x min_cell_points points) or one of unknown ground, lower than sparse_depth_m under the
    typical ground (blocks of `block` cells); or, with their sensor origins (N, 3) given, ground-like (at most
    GROUND_LIKE_M above their cell's low percentile) with a ray that runs lower than depth_m under the ground it
    crosses (each cell's own low, capped by the typical ground) at one of the horizontal distances ray_back_m back
    from the point (within the ray's length). `chunk` bounds the points ray-tested at once."""
    xyz = np.asarray(points, np.float64).reshape(-1, 3)
    origins = None if origins is None else np.broadcast_to(np.asarray(origins), xyz.shape)
    ghost = np.zeros(len(xyz), dtype=bool)
    kept = np.arange(len(xyz))
    for _ in range(max(passes, 1)):
        found = _ghost_pass(xyz if len(kept) == len(xyz) else xyz[kept], origins, kept, depth_m, cell_m, percentile,
                            min_cell_points, reach, sparse_depth_m, block, ray_back_m, chunk)
        if not found.any():
            break
        ghost[kept[found]] = True
        kept = kept[~found]
    return ghost


def _ghost_pass(xyz: np.ndarray, origins: np.ndarray | None, rows_of: np.ndarray, depth_m: float, cell_m: float,
                percentile: float, min_cell_points: int, reach: int, sparse_depth_m: float, block: int,
                ray_back_m: tuple[float, ...], chunk: int) -> np.ndarray:
    """(N,) bool: one pass of `below_ground` over xyz (N, 3), whose origins are origins[rows_of] (origins (M, 3) or
    None; rows_of (N,) int, so that no pass copies them all)."""
    low, cell, x0, y0 = cell_lows(xyz, cell_m, percentile, min_cell_points)
    if not len(cell):
        return np.zeros(0, dtype=bool)
    ground = _envelope(low, reach)
    typical_grid = typical_ground(ground, block)
    ground = np.where(np.isnan(typical_grid), ground, np.minimum(ground, typical_grid))  # unknown stays unknown
    ray_ground = np.where(np.isnan(low), ground, np.fmin(low, typical_grid))
    typical = typical_grid[cell[:, 0], cell[:, 1]]
    under = ground[cell[:, 0], cell[:, 1]] - depth_m
    ghost = xyz[:, 2] < np.where(np.isnan(under), -np.inf, under)
    flat = cell[:, 0] * ground.shape[1] + cell[:, 1]
    sparse = (np.bincount(flat, minlength=ground.size)[flat] < SPARSE_CELL_FACTOR * min_cell_points) | np.isnan(under)
    ghost |= sparse & (xyz[:, 2] < np.where(np.isnan(typical), -np.inf, typical - sparse_depth_m))
    if origins is None or not ray_back_m:
        return ghost
    own_low = low[cell[:, 0], cell[:, 1]]
    ground_like = xyz[:, 2] < np.where(np.isnan(own_low), np.inf, own_low + GROUND_LIKE_M)
    unsupported = np.flatnonzero(ground_like & ~ghost)
    highest = float(np.nanmax(ray_ground)) if np.isfinite(ray_ground).any() else -np.inf
    for start in range(0, len(unsupported), chunk):
        rows = unsupported[start:start + chunk]
        p = xyz[rows]
        toward = np.asarray(origins[rows_of[rows]], np.float64) - p
        length = np.hypot(toward[:, 0], toward[:, 1])
        rise = toward[:, 2] / np.maximum(length, 1e-9)  # height gained per metre back toward the sensor
        deep_for = np.where(rise > 0, (highest - depth_m - p[:, 2]) / np.where(rise > 0, rise, 1.0), np.inf)
        for back in ray_back_m:
            within = (length > back) & (back < deep_for) & ~ghost[rows]  # further back the ray is above every ground
            if not within.any():
                continue
            share = back / length[within]
            sample = p[within] + share[:, None] * toward[within]
            deep = sample[:, 2] < _ground_at(ray_ground, sample[:, :2], x0, y0, cell_m) - depth_m
            ghost[rows[within][deep]] = True
    return ghost
