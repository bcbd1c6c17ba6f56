"""Points below the ground (multipath ghosts: a ground return seen again further along its ray, under the road).

The ground of a point is a lower envelope of the cloud: in x-y cells of `cell_m`, a low percentile of the
heights of the cell's points (a cell needs `min_cell_points`), then the lowest of those over the
(2 * reach + 1)^2 cells around (so a cell of wall or vehicle points takes the ground of the road beside it).
Ghosts are a small share of the returns, so they do not move the percentile of a cell of real ground.

Where the real ground is hidden (behind a building, under a row of parked cars), the few ghosts landing there
still make sparse cells of their own. Points of sparse cells are therefore also tested against the typical
ground around (a median over some 15 m, which a few ghost cells do not move) with a deeper margin, and, with the
sensor origins known, by their ray: it went under the ground it crossed on the way, so a point whose ray, followed
back toward the sensor, runs lower than depth_m under a known ground is a ghost. Dense cells are never tested so:
a ramp or a cutting seen by many sweeps keeps its low ground. Frame: any frame with z up (the ego or scene frame);
metres.
"""

from __future__ import annotations

import warnings

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


def _ground_at(ground: np.ndarray, xy: np.ndarray, x0: float, y0: float, cell_m: float) -> np.ndarray:
    """(N,) the envelope's ground at x-y positions (N, 2), NaN outside it or where unknown."""
    cell = np.floor((xy - [x0, y0]) / cell_m).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < ground.shape), axis=1)
    out = np.full(len(xy), np.nan)
    out[inside] = ground[cell[inside, 0], cell[inside, 1]]
    return out


def below_ground(points: np.ndarray, depth_m: float = 0.5, cell_m: float = 1.0, percentile: float = 10.0,
                 min_cell_points: int = 5, reach: int = 2, origins: np.ndarray | None = None, sparse_depth_m: float = SPARSE_DEPTH_M, block: int = TYPICAL_BLOCK,
                 ray_back_m: tuple[float, ...] = RAY_BACK_M, chunk: int = 1_000_000) -> np.ndarray:
    """(N,) bool: ghosts among points (N, 3): lower than depth_m under their ground (`ground_envelope`); or, in a
    sparse cell (fewer than SPARSE_CELL_FACTOR x min_cell_points points) or one of unknown ground, lower than
    sparse_depth_m under the `typical_ground` around (blocks of `block` cells), or, with their sensor origins (N,
    3) given, with a ray that runs lower than depth_m under a known ground at one of the horizontal distances
    ray_back_m back from the point (within the ray's length). `chunk` bounds the points ray-tested at once."""
    ground, cell, x0, y0 = ground_envelope(points, cell_m, percentile, min_cell_points, reach)
    if not len(cell):
        return np.zeros(0, dtype=bool)
    xyz = np.asarray(points, np.float64).reshape(-1, 3)
    under = ground[cell[:, 0], cell[:, 1]] - depth_m
    ghost = xyz[:, 2] < np.where(np.isnan(under), -np.inf, under)
    flat = cell[:, 0] * ground.shape[1] + cell[:, 1]
    sparse = (np.bincount(flat, minlength=ground.size)[flat] < SPARSE_CELL_FACTOR * min_cell_points) | np.isnan(under)
    typical = typical_ground(ground, block)[cell[:, 0], cell[:, 1]] - sparse_depth_m
    ghost |= sparse & (xyz[:, 2] < np.where(np.isnan(typical), -np.inf, typical))
    if origins is None or not ray_back_m:
        return ghost
    unsupported = np.flatnonzero(sparse & ~ghost)
    origins = np.broadcast_to(np.asarray(origins, np.float64), xyz.shape)
    for start in range(0, len(unsupported), chunk):
        rows = unsupported[start:start + chunk]
        p, o = xyz[rows], origins[rows]
        toward = o - p
        length = np.hypot(toward[:, 0], toward[:, 1])
        for back in ray_back_m:
            within = (length > back) & ~ghost[rows]
            if not within.any():
                continue
            share = back / length[within]
            sample = p[within] + share[:, None] * toward[within]
            low = sample[:, 2] < _ground_at(ground, sample[:, :2], x0, y0, cell_m) - depth_m
            ghost[rows[within][low]] = True
    return ghost
