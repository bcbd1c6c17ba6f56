"""Snapping the box of a small static object onto its own points.

A box moved into a sweep's ego frame carries that frame's ego-pose error, and track refinement cannot
remove an offset that every frame of a track shares: it registers the track's frames to each other and
fixes their mean correction at zero (track_refine). For a vehicle a 0.2 m offset leaves most of its points
inside its box; for a cone, a bollard or a post, whose footprint is 0.2-0.5 m, the box misses the object
and holds no point of it. The points themselves are exact in their sweep's ego frame, and with the
refined poses the sweeps of a scene are consistent with each other, so a static object's points of all
frames, taken into its (one, static) box frame, form one cluster: the box is moved in x, y onto it.

Procedure (box frame: origin at the box centre, x along its heading, z up; metres):
1. `points_box` are the scene's points near the box, all frames, in the box frame, within `z_band_m` of
   the box's height span;
2. the local ground is the `ground_quantile` of their heights (most points around a small object are
   ground); points less than `min_height_m` above it (road, curb) or above the box's top are ignored;
3. the shift (dx, dy) within `radius_m` (lattice of `step_m`) that brings the most remaining points into
   the box footprint wins; among equal counts the smallest shift (then the first in lattice order) wins,
   so the result is deterministic and a box already holding its points does not move;
4. a box that already holds `keep_ratio` of the winning count stays: the snap is for boxes that missed
   their object, and a box holding much of it would only be pulled towards a larger neighbour.
numpy, and a compiled count of the points in each shifted footprint (numba).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np


@dataclass(frozen=True)
class BoxSnapParams:
    """max_size_m: boxes whose longer footprint side is at most this are snapped; radius_m: largest shift
    searched; step_m: lattice step of the shifts; min_height_m: points must be this far above the local
    ground (a 0.15 m curb is not an object); ground_quantile: height quantile of the points around the box
    taken as its ground; min_points: fewer object points than this leave the box where it is; z_band_m:
    see object_points; keep_ratio: see step 4 of the module docstring."""

    max_size_m: float = 1.0
    radius_m: float = 0.5
    step_m: float = 0.025
    min_height_m: float = 0.2
    ground_quantile: float = 0.3
    min_points: int = 3
    z_band_m: float = 0.5
    keep_ratio: float = 0.5


def object_points(points_box: np.ndarray, size: np.ndarray, params: BoxSnapParams) -> np.ndarray:
    """(m, 2) x, y (box frame, m) of the points of `points_box` (n, 3) that may belong to the object:
    higher than min_height_m above the local ground and not above the box top (size = [l, w, h]). Only
    points within z_band_m of the box's height span count, ground included: a canopy or a wall above a
    cone must not be taken for its ground."""
    points = np.asarray(points_box, dtype=np.float64).reshape(-1, 3)
    points = points[np.abs(points[:, 2]) <= float(size[2]) / 2.0 + params.z_band_m]
    if len(points) == 0:
        return np.zeros((0, 2))
    ground = float(np.quantile(points[:, 2], params.ground_quantile))
    top = max(float(size[2]) / 2.0, ground + float(size[2]))
    keep = (points[:, 2] > ground + params.min_height_m) & (points[:, 2] <= top)
    return points[keep, :2]


@numba.njit(cache=True)
def points_in_shifted_footprints(xy: np.ndarray, shifts: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(S,) int64: for each shift (S, 2), how many of the points xy (n, 2) lie in the footprint [-half, half]
    moved by it (box frame, m; |x - shift x| <= half x and the same in y), compiled: no (S, n) array."""
    counts = np.zeros(len(shifts), dtype=np.int64)
    for s in range(len(shifts)):
        sx, sy = shifts[s, 0], shifts[s, 1]
        for n in range(len(xy)):
            if abs(xy[n, 0] - sx) <= half[0] and abs(xy[n, 1] - sy) <= half[1]:
                counts[s] += 1
    return counts


def snap_shift(points_box: np.ndarray, size: np.ndarray, params: BoxSnapParams = BoxSnapParams()) -> np.ndarray:
    """(2,) shift (dx, dy) in the box frame (m) that moves the box footprint onto the object's points
    (module docstring); zeros when fewer than min_points object points are near."""
    xy = object_points(points_box, size, params)
    if len(xy) < params.min_points:
        return np.zeros(2)
    steps = np.arange(-params.radius_m, params.radius_m + params.step_m / 2, params.step_m)
    shifts = np.stack(np.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2)
    shifts = shifts[np.linalg.norm(shifts, axis=1) <= params.radius_m + 1e-9]
    inside = points_in_shifted_footprints(np.ascontiguousarray(xy, dtype=np.float64), shifts,
                                          np.asarray(size[:2], dtype=np.float64) / 2.0)
    at_rest = inside[np.argmin(np.linalg.norm(shifts, axis=1))]
    if inside.max() < params.min_points or at_rest >= params.keep_ratio * inside.max():
        return np.zeros(2)
    best = shifts[inside == inside.max()]
    return best[np.argmin(np.linalg.norm(best - best.mean(axis=0), axis=1))].copy()
