"""Ray consistency: how well a frame's semantic grid agrees with LiDAR returns, without any truth.

A return says "the first surface along the ray from the sensor lies here". Each return P (ego frame of the
grid, m) is walked from the ray origin O (the merged LiDAR origin in that frame) to one voxel past P by the
project's compiled traversal (`nuplan_occ.rays.traversal.mark_visible_to_first_hit`), which stops at the
first occupied voxel H (label != 0) and gives the distance d along the ray where it enters H. With
r = |P - O|, v the voxel size and V the voxel holding P, every scored return gets exactly one outcome:

- AGREE: H exists and lies at the return: within 1 voxel of V on every axis (Chebyshev distance <= 1), or H
  is a ground voxel (road, other_ground, road_line) whose height span, grown by one voxel, holds P's height.
  The second case is the grazing ray: a ray meeting the road at a few degrees runs through the voxel layer
  that holds the road for metres before it reaches the surface (up to v / sin(elevation) along the ray),
  so a correct road stops it early by a distance that measures the angle, not an error.
- EARLY: H exists, does not lie at the return, and the ray enters it more than EARLY_M before the return
  (r - d > EARLY_M): floaters, ghosts, doubled surfaces, trails of moving things, a wall drawn in front.
- HOLE: no occupied voxel along the ray up to one voxel past P, and none of V's 26 neighbours nor V itself
  is occupied: the grid has nothing where the LiDAR saw a surface.
- OTHER: the rest (H up to EARLY_M before the return but not at it; or the ray passing beside an occupied
  neighbour of V): a surface displaced by more than a voxel and less than EARLY_M.

Depth error of a return with an H: 0 when H lies at the return, else r - d (m, how early the ray ended;
negative never arises, since a hit past P is within a voxel of V). Returns without H have none.

Scored returns: those inside the grid's box and farther than one voxel from O (a return outside the grid
cannot be checked against it; a ray too short to cross a voxel says nothing). With max_rays, only every k-th
return given is considered, k = `return_stride` (the smallest stride leaving at most max_rays of them), so a
caller may stride a sweep before moving it into the grid's frame and get the same figures.
Rays are straight lines from O: returns of LiDARs mounted elsewhere on the vehicle are treated as if seen
from the merged origin (as the build's LiDAR mask treats them).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import EMPTY, OTHER_GROUND, ROAD, ROAD_LINE
from nuplan_occ.rays.traversal import NUDGE_VOXELS, grid_args, mark_visible_to_first_hit

EARLY_M = 1.0
"""A ray ending more than this before its return (m) counts as EARLY."""

GROUND_IDS = (ROAD, OTHER_GROUND, ROAD_LINE)
"""Labels of horizontal surfaces, which rays may graze (see AGREE)."""

AGREE, EARLY, HOLE, OTHER = 0, 1, 2, 3
"""Outcome codes of a scored return."""

NOT_SCORED = -1
"""Outcome code of a return outside the grid or within a voxel of the origin."""

FLAG_RULES = {
    "rays_early": ("early", ">", 0.10),
    "rays_holes": ("hole", ">", 0.02),
    "rays_disagree": ("agree", "<", 0.85),
}
"""Frame flag rules: name -> (RayConsistency field, comparison, threshold); shares of the scored returns."""


@dataclass(frozen=True)
class RayConsistency:
    """One frame's figures: n_returns given, n_scored (of the returns max_rays leaves, those inside the grid
    and farther than a voxel), shares of the scored returns per outcome (agree + early + hole + other = 1; NaN without
    scored returns), and quantiles of the depth error (m) over the scored returns with a first hit."""

    n_returns: int
    n_scored: int
    agree: float
    early: float
    hole: float
    other: float
    depth_error_p90_m: float
    depth_error_p99_m: float

    def to_dict(self) -> dict:
        return asdict(self)


def return_stride(n_returns: int, max_rays: int | None) -> int:
    """The stride k leaving at most max_rays of n_returns returns (1 for None or enough)."""
    return 1 if max_rays is None or n_returns <= max_rays else int(np.ceil(n_returns / max_rays))


def _scored(returns: np.ndarray, origin: np.ndarray, grid: GridSpec, max_rays: int | None) -> np.ndarray:
    """Indices of the scored returns (module docstring)."""
    index = np.arange(0, len(returns), return_stride(len(returns), max_rays))
    points = returns[index]
    inside = np.all((points >= grid.lower) & (points < grid.upper), axis=1)
    far = np.einsum("ij,ij->i", points - origin, points - origin) > grid.voxel_size ** 2
    return index[inside & far]


def _voxel_at(starts: np.ndarray, ends: np.ndarray, t: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(N, 3) int64 index of the voxel each segment enters at t, evaluated as the traversal evaluates an
    entry (a nudge after t, in voxel units)."""
    o = (starts - grid.lower) / grid.voxel_size
    d = (ends - grid.lower) / grid.voxel_size - o
    nudge = NUDGE_VOXELS / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    return np.floor(o + (t + nudge)[:, None] * d).astype(np.int64)


def _neighbourhood_occupied(occupied: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(N,) whether any voxel within Chebyshev distance 1 of each index (N, 3) is occupied (bool grid)."""
    shape = np.array(occupied.shape)
    found = np.zeros(len(index), dtype=bool)
    for offset in np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), axis=-1).reshape(-1, 3):
        cell = index + offset
        valid = np.all((cell >= 0) & (cell < shape), axis=1)
        found[valid] |= occupied[tuple(cell[valid].T)]
    return found


def ray_outcomes(semantics: np.ndarray, origin: np.ndarray, returns: np.ndarray, grid: GridSpec,
                 max_rays: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(outcome (N,) int8: AGREE, EARLY, HOLE, OTHER or NOT_SCORED; depth error (N,) m, NaN where the return
    is not scored or its ray meets no occupied voxel) of every return (module docstring).

    semantics: uint8 (X, Y, Z) of `grid` (0 = empty); origin (3,) and returns (N, 3): metres, the grid's ego
    frame; max_rays: consider every `return_stride`-th return only (None: all).
    """
    returns = np.asarray(returns, dtype=np.float64).reshape(-1, 3)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    outcome = np.full(len(returns), NOT_SCORED, dtype=np.int8)
    depth_error = np.full(len(returns), np.nan)
    index = _scored(returns, origin, grid, max_rays)
    if not len(index):
        return outcome, depth_error
    points = returns[index]
    r = np.linalg.norm(points - origin, axis=1)
    direction = (points - origin) / r[:, None]
    ends = points + grid.voxel_size * direction
    starts = np.broadcast_to(origin, ends.shape).copy()
    lower, voxel_size, shape = grid_args(grid)
    flat = np.ascontiguousarray(semantics).reshape(-1)
    occupied = flat != EMPTY
    n = len(points)
    stop_t, reached = np.zeros(n), np.zeros(n, dtype=bool)
    mark_visible_to_first_hit(starts, ends, lower, voxel_size, shape, occupied, 0.0, np.zeros(n),
                              np.zeros(occupied.size, dtype=bool), reached, stop_t)
    hit_index = _voxel_at(starts, ends, stop_t, grid)
    hit = ~reached & np.all((hit_index >= 0) & (hit_index < np.array(shape)), axis=1)
    hit[hit] = occupied.reshape(semantics.shape)[tuple(hit_index[hit].T)]
    own_index, _ = grid.point_to_index(points)
    chebyshev = np.max(np.abs(hit_index - own_index), axis=1)
    hit_label = np.zeros(n, dtype=np.uint8)
    hit_label[hit] = semantics[tuple(hit_index[hit].T)]
    z_low = grid.z_min + hit_index[:, 2] * voxel_size
    grazing = np.isin(hit_label, GROUND_IDS) & (points[:, 2] >= z_low - voxel_size) & \
        (points[:, 2] < z_low + 2 * voxel_size)
    at_return = hit & ((chebyshev <= 1) | grazing)
    ahead = r - stop_t * (r + voxel_size)  # how far before the return the ray entered its first hit
    codes = np.full(n, OTHER, dtype=np.int8)
    codes[at_return] = AGREE
    codes[hit & ~at_return & (ahead > EARLY_M)] = EARLY
    missed = ~hit
    missed[missed] = ~_neighbourhood_occupied(occupied.reshape(semantics.shape), own_index[missed])
    codes[missed] = HOLE
    outcome[index] = codes
    depth_error[index[hit]] = np.where(at_return[hit], 0.0, ahead[hit])
    return outcome, depth_error


def broken_rules(figures: dict[str, float]) -> list[str]:
    """Names of the FLAG_RULES a frame's figures (field -> value; missing or NaN: not judged) break."""
    broken = []
    for name, (key, comparison, threshold) in FLAG_RULES.items():
        value = figures.get(key)
        if value is not None and np.isfinite(value) and ((value > threshold) if comparison == ">" else
                                                         (value < threshold)):
            broken.append(name)
    return broken


def summarize(outcome: np.ndarray, depth_error: np.ndarray) -> RayConsistency:
    """A frame's figures from `ray_outcomes`' per-return arrays."""
    scored = outcome != NOT_SCORED
    n = int(np.count_nonzero(scored))
    share = (lambda code: float(np.count_nonzero(outcome == code) / n)) if n else (lambda code: float("nan"))
    errors = depth_error[scored & np.isfinite(depth_error)]
    p90, p99 = (np.quantile(errors, [0.9, 0.99]) if len(errors) else (np.nan, np.nan))
    return RayConsistency(len(outcome), n, share(AGREE), share(EARLY), share(HOLE), share(OTHER),
                          float(p90), float(p99))


def ray_consistency(semantics: np.ndarray, origin: np.ndarray, returns: np.ndarray, grid: GridSpec,
                    max_rays: int | None = None) -> RayConsistency:
    """The frame's ray-consistency figures (module docstring; arguments as `ray_outcomes`)."""
    return summarize(*ray_outcomes(semantics, origin, returns, grid, max_rays))
