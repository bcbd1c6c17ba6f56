"""Boxes fitted to their track's points: the object's points decide its extent, the box its label and pose.

An auto-labelled box can be too small for its object (it would cut the object off) or too large (its empty part
would be drawn solid: the space carving only clears what rays to the object's own points crossed, and nothing
crosses the air above a truck, where the sky gives no return). Both are read from the track's points gathered
over all its sweeps in its corrected box frame (origin at the box centre, x along the heading, z up; metres):
- grow: each half extent grows to the `quantile` of the points' |x|, |y| and z, by at most a margin per side;
- shrink: each half extent shrinks to the `shrink_quantile` of the same plus `pad_m` (a higher quantile: the
  parts of an object few sweeps saw, a truck's body below the cars around it, are a small share of its points),
  by at most `max_shrink` of the extent, and the bottom rises to the low quantile of all the box's points (the
  road under a box reaching below it) less pad_m, by at most `floor_clearance_m`: a box's floor band is where its
  road lies, and an object whose lower part few returns saw (a truck behind parked cars) keeps it. The top may
  also rise, by at most `raise_max_m`, to hold the points above a box too low for its object (its roof): only
  the top, since the points above a box are seen, where a side grown about the centre would be guessed.
Both are symmetric about the box centre in x and y, so an object seen from one side keeps its hidden half, and a
centre off by d keeps d more on each side rather than cutting the object. Points within `floor_clearance_m` of the
box's bottom (of the ground under it, for a shrink) are the ground, not the object, for every extent but the
bottom's. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from nuplan_occ.aggregation.carve import body_points
from nuplan_occ.io.types import Boxes


@dataclass(frozen=True)
class BoxFitParams:
    """grow_margin_m: largest growth per side (m; 0: no growing); grow_categories: categories whose boxes may grow;
    shrink_categories: categories whose boxes may shrink; max_shrink: largest share of an extent a shrink removes
    (0: no shrinking); pad_m: room left beyond the points' quantile (m); floor_clearance_m: points this close
    above the box's bottom are the ground (m); quantile: of the points' reach for a grow, so that a few stray
    returns around a box do not widen it; shrink_quantile: the same for a shrink, so that they do not hold it
    open; min_points: a track with fewer object points over its sweeps keeps its box; raise_max_m: largest rise
    of the top of a box of shrink_categories to hold its points (m; 0: none)."""

    grow_margin_m: float = 0.15
    grow_categories: tuple[str, ...] = ("pedestrian",)
    shrink_categories: tuple[str, ...] = ("vehicle",)
    max_shrink: float = 0.25
    pad_m: float = 0.1
    floor_clearance_m: float = 0.3
    quantile: float = 0.99
    shrink_quantile: float = 0.999
    min_points: int = 20
    raise_max_m: float = 0.2


@dataclass(frozen=True)
class FittedExtent:
    """A track's box extent from its points, in its median box's frame (m): half (3,) = half length, half width
    and half height; z_shift: the fitted box centre's height above the median box's centre; sides: the length and
    width are fitted too (False: each box keeps its own, only its height and centre change)."""

    half: np.ndarray
    z_shift: float
    sides: bool = True


def _reach(body: np.ndarray, quantile: float) -> np.ndarray:
    return np.array([np.quantile(np.abs(body[:, 0]), quantile), np.quantile(np.abs(body[:, 1]), quantile),
                     np.quantile(body[:, 2], quantile)])


def grown_extent(points: np.ndarray, size: np.ndarray, params: BoxFitParams) -> FittedExtent | None:
    """The extent of a box of `size` (3,) grown to hold its track's points (n, 3), box frame, gathered in the box
    grown by params.grow_margin_m; None when the points are too few or already fit. Growth is symmetric about the
    centre in z too (z_shift 0)."""
    size = np.asarray(size, np.float64)
    body = body_points(points, size, params.floor_clearance_m)
    if len(body) < params.min_points:
        return None
    growth = np.clip(_reach(body, params.quantile) - size / 2, 0.0, params.grow_margin_m)
    if not np.any(growth > 0):
        return None
    return FittedExtent(size / 2 + growth, 0.0)


def shrunk_extent(points: np.ndarray, size: np.ndarray, params: BoxFitParams) -> FittedExtent | None:
    """The extent of a box of `size` (3,) shrunk to its track's points (n, 3), box frame, gathered in the box
    with its top raised by params.raise_max_m: the points inside the box decide the sides and the bottom, a top
    they fill rises to the points above it; None when the points are too few or fill the box exactly."""
    size = np.asarray(size, np.float64)
    half = size / 2
    if len(points) < params.min_points or params.max_shrink <= 0:
        return None
    in_box = points[:, 2] <= half[2]
    if not in_box.any():
        return None
    low = max(float(np.quantile(points[in_box, 2], 1.0 - params.shrink_quantile)), -half[2])
    above_floor = points[:, 2] > low + params.floor_clearance_m
    body = points[above_floor & in_box]
    if len(body) < params.min_points:
        return None
    floor = half * (1.0 - params.max_shrink)
    reach = _reach(body, params.shrink_quantile) + params.pad_m
    new_half_xy = np.clip(reach[:2], floor[:2], half[:2])
    bottom = float(np.clip(low - params.pad_m, -half[2], -half[2] + params.floor_clearance_m))
    if reach[2] >= half[2]:  # the top is filled: it rises to the points above it
        reach[2] = np.quantile(points[above_floor, 2], params.shrink_quantile) + params.pad_m
    top = float(np.clip(reach[2], bottom, half[2] + params.raise_max_m))
    height = max(top - bottom, 2 * floor[2])
    bottom = min(bottom, top - height)
    sides = not np.allclose(new_half_xy, half[:2], rtol=0.0, atol=1e-9)
    if not sides and np.allclose([bottom, top], [-half[2], half[2]], rtol=0.0, atol=1e-9):
        return None
    return FittedExtent(np.r_[new_half_xy, height / 2], float((top + bottom) / 2), sides)


def _gather(boxes: dict[int, Boxes], xyz_of, origin: np.ndarray, params: BoxFitParams
            ) -> tuple[dict[str, list[np.ndarray]], dict[str, np.ndarray], dict[str, str]]:
    """(track -> its box-frame points per sweep, track -> median size, track -> category) of the tracks of the
    fitted categories, their points gathered in boxes grown by grow_margin_m for grow_categories and with the top
    raised by raise_max_m for the other shrink_categories (the points stay in the frame of the box as given)."""
    from nuplan_occ.aggregation.split import points_per_box

    fitted = set(params.grow_categories) | set(params.shrink_categories)
    views: dict[str, list[np.ndarray]] = {}
    sizes: dict[str, list[np.ndarray]] = {}
    category: dict[str, str] = {}
    for i, b in boxes.items():
        chosen = np.array([c in fitted for c in b.categories], dtype=bool)
        if not chosen.any():
            continue
        picked = b.subset(chosen)
        for track, size, c in zip(picked.track_tokens, picked.sizes, picked.categories):
            sizes.setdefault(track, []).append(size)
            category[track] = c
        grow = np.array([c in params.grow_categories for c in picked.categories], dtype=bool)
        rise = params.raise_max_m * np.array([c in params.shrink_categories for c in picked.categories]) * ~grow
        up = rise[:, None] * [0.0, 0.0, 1.0]
        picked = replace(picked, sizes=picked.sizes + 2.0 * params.grow_margin_m * grow[:, None] + up,
                         centers=picked.centers + up / 2)
        lift = dict(zip(picked.track_tokens, rise / 2))
        for track, (points, _) in points_per_box(xyz_of(i), picked, origin).items():
            views.setdefault(track, []).append(points + [0.0, 0.0, lift[track]])
    return views, {track: np.median(np.stack(s), axis=0) for track, s in sizes.items()}, category


def fitted_extents(boxes: dict[int, Boxes], xyz_of, origin: np.ndarray, params: BoxFitParams) -> dict[str, FittedExtent]:
    """track -> its fitted extent (`grown_extent` for grow_categories, `shrunk_extent` for shrink_categories, a
    category in both tries growing first) from sweep -> Boxes (ego frames), xyz_of(i): sweep i's points (N, 3),
    ego frame (read once per sweep); origin: the sensor origin (3,), ego frame. Tracks whose box stays are left
    out."""
    if not (params.grow_margin_m > 0 and params.grow_categories) and not (params.max_shrink > 0
                                                                            and params.shrink_categories):
        return {}
    views, sizes, category = _gather(boxes, xyz_of, origin, params)
    fitted = {}
    for track, per_sweep in views.items():
        points = np.vstack([p for p in per_sweep if len(p)] or [np.zeros((0, 3))])
        extent = None
        if params.grow_margin_m > 0 and category[track] in params.grow_categories:
            extent = grown_extent(points, sizes[track], params)
        if extent is None and category[track] in params.shrink_categories:
            extent = shrunk_extent(points, sizes[track], params)
        if extent is not None:
            fitted[track] = extent
    return fitted


def fitted_boxes(boxes: dict[int, Boxes], extents: dict[str, FittedExtent]) -> dict[int, Boxes]:
    """sweep -> Boxes with each fitted track's boxes given its extent (`fitted_extents`): size 2 * half (the height
    only, for an extent whose sides were not fitted), centre raised by z_shift (boxes are upright in their frame, so
    the box's z is the frame's)."""
    if not extents:
        return boxes
    out = {}
    for i, b in boxes.items():
        sizes, centers = b.sizes.copy(), b.centers.copy()
        for k, track in enumerate(b.track_tokens):
            if track in extents:
                fitted = 2.0 * extents[track].half
                sizes[k] = fitted if extents[track].sides else [sizes[k, 0], sizes[k, 1], fitted[2]]
                centers[k, 2] += extents[track].z_shift
        out[i] = replace(b, sizes=sizes, centers=centers)
    return out
