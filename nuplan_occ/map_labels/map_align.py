"""Align the vector map to the LiDAR's painted lines: a 2D rigid correction of the scene's poses against
the map (numpy, shapely 2 and numba kernels).

Relative poses after registration agree to about a millimetre, but the scene as a whole can sit a few
centimetres (synthetic logs) to decimetres (real logs: GNSS/INS error, map survey error) off the map. The
painted lines are 0.15 m wide, so such an offset moves them to the neighbouring voxels. Paint is far more
reflective than asphalt (retroreflective beads), so ground returns whose intensity is well above that of
the ground at the same range mark the painted strips. Aligning them to the map's line geometries by a
robust 2D point-to-line ICP (x, y, yaw) gives the correction. A point's nearest line is found among the
line pieces within reach of it (`nuplan_occ.map_labels.line_segments`), found once and looked up again only
for points that moved more than CANDIDATE_SLACK_M since.

Frames: points "ego" are in a sweep's ego frame (metres); "global" is the map's frame (UTM metres). The
correction C is a 4x4 transform acting in the global frame: T_global_from_ego(corrected) = C @ T_global_from_ego.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import shapely
from scipy import ndimage

from nuplan_occ.geometry import transform_points
from nuplan_occ.io.types import PointCloud
from nuplan_occ.sequences import MappedSequence
from nuplan_occ.map_labels.line_segments import NearPieces, Pieces, signed_offsets

CANDIDATE_SLACK_M = 1.0
"""Line pieces are looked up this far beyond the gate around the points, so the refinement's moves (at most
max_offset_m plus its yaw's sweep) rarely need a second lookup."""


@dataclass(frozen=True)
class MapAlignment:
    """Result of `align_points_to_lines`. dx, dy: metres (global frame); dyaw: radians about `pivot`
    (global x, y); n_points: paint points used in the last iteration; rms_before / rms_after: RMS
    point-to-line distance (m) of the used points before and after; applied: False when the correction was
    refused (then `reason` says why and the correction is the identity)."""

    dx: float
    dy: float
    dyaw: float
    pivot: tuple[float, float]
    n_points: int
    rms_before: float
    rms_after: float
    applied: bool
    reason: str = ""

    @property
    def correction(self) -> np.ndarray:
        """4x4 transform C (global -> corrected global): rotation by dyaw about the pivot, then (dx, dy)."""
        C = np.eye(4)
        if not self.applied:
            return C
        c, s = np.cos(self.dyaw), np.sin(self.dyaw)
        R = np.array([[c, -s], [s, c]])
        pivot = np.asarray(self.pivot)
        C[:2, :2] = R
        C[:2, 3] = pivot - R @ pivot + np.array([self.dx, self.dy])
        return C


@dataclass(frozen=True)
class FlatColumns:
    """Which cell_m x cell_m columns of some clouds (one frame, m) are flat ground (see `flat_columns`).
    flat[i, j] is the column of cell index first_cell + (i, j), cells counted from the frame's origin."""

    flat: np.ndarray
    first_cell: np.ndarray
    cell_m: float

    def of(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: the points (N, 3) of the clouds the columns were made of that lie in a flat column."""
        if len(points) == 0:
            return np.zeros(0, dtype=bool)
        cells = _cells(points, self.cell_m) - self.first_cell
        return self.flat[cells[:, 0], cells[:, 1]]


def _cells(points: np.ndarray, cell_m: float) -> np.ndarray:
    return np.floor(np.asarray(points, dtype=np.float64)[:, :2] / cell_m).astype(np.int64)


def _cell_range(points: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The least and greatest `_cells` of the points (N >= 1), from their coordinates' extremes (floor is
    monotonic, so these are the cells' own extremes)."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    low = np.floor(np.array([xy[:, 0].min(), xy[:, 1].min()]) / cell_m).astype(np.int64)
    high = np.floor(np.array([xy[:, 0].max(), xy[:, 1].max()]) / cell_m).astype(np.int64)
    return low, high


def _column_extremes(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat lowest (+inf) and highest (-inf) height per column of a (shape) column grid, to be filled."""
    return np.full(shape[0] * shape[1], np.inf), np.full(shape[0] * shape[1], -np.inf)


def _add_heights(lowest: np.ndarray, highest: np.ndarray, ny: int, cells: np.ndarray, heights: np.ndarray) -> None:
    """Lower `lowest` and raise `highest` (flat, ny columns per row) by the heights at the grid cells (N, 2)."""
    flat = cells[:, 0] * ny + cells[:, 1]
    np.minimum.at(lowest, flat, heights)
    np.maximum.at(highest, flat, heights)


def _flat_mask(lowest: np.ndarray, highest: np.ndarray, shape: tuple[int, int], flatness_m: float) -> np.ndarray:
    """(shape) bool: columns whose 3x3 neighbourhood spans at most flatness_m in height."""
    lowest = ndimage.minimum_filter(lowest.reshape(shape), size=3, mode="nearest")
    highest = ndimage.maximum_filter(highest.reshape(shape), size=3, mode="nearest")
    return highest - lowest <= flatness_m


def flat_columns(clouds: Sequence[np.ndarray], cell_m: float = 0.5, flatness_m: float = 0.06) -> FlatColumns:
    """The columns of the clouds (each (N_i, 3), one frame, m, read twice) whose cell and its 8 neighbours
    hold only points within flatness_m of each other in height, over all clouds together: open, flat ground.
    Columns at a curb, a wall foot, an object or vegetation are left out (their returns are bright for other
    reasons than paint: a curb's face and edge are seen head-on). Holds one cloud at a time."""
    low, high = np.full(2, np.iinfo(np.int64).max), np.full(2, np.iinfo(np.int64).min)
    for points in clouds:
        if len(points):
            cloud_low, cloud_high = _cell_range(points, cell_m)
            low, high = np.minimum(low, cloud_low), np.maximum(high, cloud_high)
    if np.any(low > high):
        return FlatColumns(np.zeros((0, 0), dtype=bool), np.zeros(2, dtype=np.int64), cell_m)
    first = low - 1  # a column of no points all around: the filters below see no edge effects
    shape = (int(high[0] - first[0] + 2), int(high[1] - first[1] + 2))
    lowest, highest = _column_extremes(shape)
    for points in clouds:
        if len(points):
            _add_heights(lowest, highest, shape[1], _cells(points, cell_m) - first,
                         np.asarray(points, dtype=np.float64)[:, 2])
    return FlatColumns(_flat_mask(lowest, highest, shape, flatness_m), first, cell_m)


def flat_ground(points_ego: np.ndarray, cell_m: float = 0.5, flatness_m: float = 0.06) -> np.ndarray:
    """(N,) bool: points (N, 3, ego frame, m) in a flat-ground column of their own cloud (`flat_columns`)."""
    if len(points_ego) == 0:
        return np.zeros(0, dtype=bool)
    cells = _cells(points_ego, cell_m)
    cells -= cells.min(axis=0) - 1
    shape = (int(cells[:, 0].max()) + 2, int(cells[:, 1].max()) + 2)
    lowest, highest = _column_extremes(shape)
    _add_heights(lowest, highest, shape[1], cells, np.asarray(points_ego, dtype=np.float64)[:, 2])
    return _flat_mask(lowest, highest, shape, flatness_m)[cells[:, 0], cells[:, 1]]


def intensity_ratio(points_ego: np.ndarray, intensity: np.ndarray, sensor_origin_ego: np.ndarray,
                    range_bin_m: float = 2.0, min_per_bin: int = 20) -> np.ndarray:
    """(N,) intensity of each point of one sweep divided by the median intensity of the sweep's flat-ground
    points (see `flat_ground`) at the same horizontal range from the sensor (bins of range_bin_m; intensity
    falls with range and incidence); NaN in bins with fewer than min_per_bin flat-ground points.
    points_ego: (N, 3) ego frame, m; sensor_origin_ego: (3,) m."""
    points_ego = np.asarray(points_ego, dtype=np.float64)
    intensity = np.asarray(intensity, dtype=np.float64)
    ratio = np.full(len(points_ego), np.nan)
    if len(points_ego) == 0:
        return ratio
    ground = flat_ground(points_ego)
    bins = np.floor(np.linalg.norm(points_ego[:, :2] - np.asarray(sensor_origin_ego)[None, :2], axis=1)
                    / range_bin_m).astype(np.int64)
    ground_bins, ground_intensity = bins[ground], intensity[ground]
    by_intensity = np.argsort(ground_intensity)
    order = by_intensity[np.argsort(ground_bins[by_intensity], kind="stable")]  # by bin, then by intensity
    sorted_bins, sorted_intensity = ground_bins[order], ground_intensity[order]
    bin_ids, starts, counts = np.unique(sorted_bins, return_index=True, return_counts=True)
    upper = sorted_intensity[starts + counts // 2]
    lower = sorted_intensity[starts + (counts - 1) // 2]
    medians = (lower + upper) / 2.0  # np.median's middle value, or mean of the middle two
    usable = (counts >= min_per_bin) & (medians > 0)
    bin_ids, medians = bin_ids[usable], medians[usable]
    slot = np.minimum(np.searchsorted(bin_ids, bins), max(len(bin_ids) - 1, 0))
    has = (bin_ids[slot] == bins) if len(bin_ids) else np.zeros(len(bins), dtype=bool)
    ratio[has] = intensity[has] / medians[slot[has]]
    return ratio


@dataclass(frozen=True)
class GroundReturns:
    """Flat-ground returns of a scene's sweeps: xy (M, 2) global frame, m; bright (M,) bool: looks like paint."""

    xy: np.ndarray
    bright: np.ndarray

    def moved(self, correction: np.ndarray) -> "GroundReturns":
        """The returns moved by a 4x4 global-frame correction (see MapAlignment.correction)."""
        return GroundReturns(self.xy @ correction[:2, :2].T + correction[:2, 3], self.bright)


def ground_returns(clouds_ego: Sequence[PointCloud], T_global_from_ego: np.ndarray, sensor_origin_ego: np.ndarray,
                   ratio: float = 3.0) -> GroundReturns:
    """The sweeps' returns on ground that is flat in all sweeps together (`flat_columns` of the merged cloud,
    dense enough to reveal every curb), each marked bright (paint) when at least `ratio` times brighter than
    the flat ground at its range in its own sweep.
    clouds_ego[i]: sweep i in its ego frame (xyz m, intensity; any sequence, each read three times, one at a
    time); T_global_from_ego: (S, 4, 4) the sweeps' poses."""
    T = np.asarray(T_global_from_ego, dtype=np.float64)
    placed = MappedSequence(range(len(clouds_ego)), lambda k: transform_points(T[k], clouds_ego[k].xyz))
    columns = flat_columns(placed)
    xy, bright = [np.zeros((0, 2))], [np.zeros(0, dtype=bool)]
    for k, cloud in enumerate(clouds_ego):
        points = transform_points(T[k], cloud.xyz)
        flat = columns.of(points)
        with np.errstate(invalid="ignore"):
            bright.append((intensity_ratio(cloud.xyz, cloud.intensity, sensor_origin_ego) >= ratio)[flat])
        xy.append(points[flat, :2])
    return GroundReturns(np.vstack(xy), np.concatenate(bright))


def polygon_edges(polygons: np.ndarray) -> np.ndarray:
    """Object array of every straight edge (2-point LineString) of the polygons' outlines."""
    edges = []
    for ring in shapely.get_parts(shapely.boundary(np.asarray(polygons, dtype=object))):
        coords = shapely.get_coordinates(ring)
        edges.extend(shapely.linestrings(np.stack([coords[:-1], coords[1:]], axis=1)))
    return np.asarray([e for e in edges if shapely.length(e) > 1e-6], dtype=object)


def paint_confirmed(lines: np.ndarray, returns: GroundReturns, width_m: float, min_bright_fraction: float = 0.5,
                    min_returns: int = 10) -> np.ndarray:
    """(L,) bool: lines (global frame) whose painted strip (width_m, plus 0.05 m either side) holds at least
    min_returns flat-ground returns, at least min_bright_fraction of them bright. A line never observed, or
    observed as bare asphalt, is not confirmed."""
    lines = np.asarray(lines, dtype=object).reshape(-1)
    if len(lines) == 0 or len(returns.xy) == 0:
        return np.zeros(len(lines), dtype=bool)
    strips = shapely.buffer(lines, width_m / 2.0 + 0.05, cap_style="flat")
    near = shapely.intersects_xy(shapely.union_all(strips), returns.xy[:, 0], returns.xy[:, 1])
    points = shapely.points(returns.xy[near])
    line_index, point_index = shapely.STRtree(points).query(strips, predicate="contains")
    total = np.bincount(line_index, minlength=len(lines))
    bright = np.bincount(line_index, weights=returns.bright[near][point_index], minlength=len(lines))
    return (total >= min_returns) & (bright >= min_bright_fraction * np.maximum(total, 1))


@numba.njit(cache=True)
def _inlier_counts(starts: np.ndarray, normal: np.ndarray, residual: np.ndarray, offset_x: np.ndarray,
                   offset_y: np.ndarray, inlier_m: float) -> np.ndarray:
    """(O,) per translation (offset_x[o], offset_y[o]): the points (pair groups [starts[g], starts[g + 1]) of
    the rows of normal (K, 2), residual (K,)) with a pair within inlier_m of its line after the move. The
    offsets are the inner loop, without branches, so it vectorizes."""
    counts = np.zeros(len(offset_x), np.int64)
    hit = np.zeros(len(offset_x), np.int64)
    for g in range(len(starts) - 1):
        hit[:] = 0
        for k in range(starts[g], starts[g + 1]):
            r, nx, ny = residual[k], normal[k, 0], normal[k, 1]
            for o in range(len(offset_x)):
                hit[o] |= abs(r + (nx * offset_x[o] + ny * offset_y[o])) <= inlier_m
        counts += hit
    return counts


def _best_translation(point_index: np.ndarray, normal: np.ndarray, residual: np.ndarray, search_m: float,
                      step_m: float, inlier_m: float) -> np.ndarray:
    """The translation (2,) on a square grid of half size search_m (step step_m) that puts the most points
    within inlier_m of a line (pairs (point index sorted, the line's unit normal, the point's signed
    distance); a point moved by a small d then lies at residual + normal . d from that line); among equal
    counts the smallest translation (directions the lines leave free stay at zero)."""
    axis = np.arange(-search_m, search_m + step_m / 2, step_m)
    offsets = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1).reshape(-1, 2)
    starts = np.flatnonzero(np.r_[True, point_index[1:] != point_index[:-1], True])
    counts = _inlier_counts(starts, normal, residual, np.ascontiguousarray(offsets[:, 0]),
                            np.ascontiguousarray(offsets[:, 1]), inlier_m)
    tied = np.flatnonzero(counts >= counts.max())
    return offsets[tied[np.argmin(np.linalg.norm(offsets[tied], axis=1))]]


def align_points_to_lines(points_xy_global: np.ndarray, lines: np.ndarray, max_offset_m: float = 0.5,
                          max_yaw_deg: float = 1.0, paint_half_width_m: float = 0.075, search_step_m: float = 0.02,
                          gate_m: float = 0.15,
                          huber_m: float = 0.05, prior_fraction: float = 0.01, min_points: int = 200,
                          iterations: int = 10) -> MapAlignment:
    """2D rigid correction moving paint points onto the map's painted lines.

    points_xy_global: (N, 2) paint-candidate points, global frame (m). lines: array of shapely LineStrings
    (global frame): the painted lines' centre lines.
    1. Translation search: the translation within max_offset_m (grid step search_step_m) that puts the most
       points within paint_half_width_m of a line. Counting inliers, unlike least squares, is not pulled by
       bright returns that are not paint (a curb top next to an edge line).
    2. Refinement from there: each iteration matches every point within gate_m of a line to its nearest
       line point and solves the linearized point-to-line least squares in (dx, dy, dyaw) with Huber weights
       (huber_m) and a weak prior toward the found translation and zero yaw (as strong as prior_fraction of
       the points constraining each of dx, dy and the yaw's motion at the points' RMS radius; it keeps
       directions the lines do not constrain, e.g. along a straight road, where the search left them).
    The correction is refused (identity, `applied` False, `reason` set) with fewer than min_points points
    near a line, or when its translation exceeds max_offset_m or its rotation max_yaw_deg."""
    xy = np.asarray(points_xy_global, dtype=np.float64).reshape(-1, 2)
    lines = np.asarray([g for g in np.asarray(lines, dtype=object).reshape(-1)
                        if g is not None and not shapely.is_empty(g)], dtype=object)
    pivot = np.asarray(xy.mean(axis=0) if len(xy) else (0.0, 0.0))
    refused = dict(dx=0.0, dy=0.0, dyaw=0.0, pivot=(float(pivot[0]), float(pivot[1])), applied=False)
    if len(xy) < min_points or len(lines) == 0:
        return MapAlignment(n_points=0, rms_before=float("nan"), rms_after=float("nan"), **refused,
                            reason=f"too few paint points ({len(xy)}) or no painted lines")
    pieces = Pieces.of(lines)
    reach = max_offset_m + paint_half_width_m
    near = NearPieces(pieces, xy, max(reach, gate_m + CANDIDATE_SLACK_M), gate_m, CANDIDATE_SLACK_M)
    point_index, piece_index = near.pairs(reach)
    normal, residual = signed_offsets(xy[point_index], piece_index, pieces.starts, pieces.ends)
    dist_before = near.nearest(xy)[1]
    near_before = dist_before <= gate_m
    rms_before = _rms(dist_before[near_before])
    if len(np.unique(point_index)) < min_points:
        return MapAlignment(n_points=int(near_before.sum()), rms_before=rms_before, rms_after=float("nan"),
                            **refused, reason=f"only {len(np.unique(point_index))} paint points near a line")
    start = _best_translation(point_index, normal, residual, max_offset_m, search_step_m, paint_half_width_m)
    local = xy - pivot
    params = np.array([start[0], start[1], 0.0])  # dx, dy, dyaw
    anchor = params.copy()
    for _ in range(max(1, iterations)):
        moved = _moved(local, params) + pivot
        which, dist = near.nearest(moved)
        used = dist <= gate_m
        if used.sum() < min_points:
            return MapAlignment(n_points=int(used.sum()), rms_before=rms_before, rms_after=float("nan"), **refused,
                                reason=f"only {int(used.sum())} paint points within {gate_m} m of a line")
        normal_used, res = signed_offsets(moved[used], which[used], pieces.starts, pieces.ends)
        arm = moved[used] - pivot - params[:2]  # rotated local offsets
        J = np.stack([normal_used[:, 0], normal_used[:, 1],
                      -arm[:, 1] * normal_used[:, 0] + arm[:, 0] * normal_used[:, 1]], axis=1)
        weight = np.where(np.abs(res) <= huber_m, 1.0, huber_m / np.maximum(np.abs(res), 1e-12))
        radius = max(float(np.sqrt(np.mean(np.sum(arm**2, axis=1)))), 1.0)
        prior = prior_fraction * weight.sum() * np.diag([1.0, 1.0, radius**2])
        step = np.linalg.solve(J.T @ (weight[:, None] * J) + prior, -J.T @ (weight * res) - prior @ (params - anchor))
        params = params + step
        if np.abs(step[:2]).max() < 1e-4 and abs(step[2]) < 1e-6:
            break
    dist_after = near.nearest(_moved(local, params) + pivot)[1]
    shift, turn = float(np.hypot(params[0], params[1])), float(np.degrees(abs(params[2])))
    if shift > max_offset_m or turn > max_yaw_deg:
        return MapAlignment(n_points=int(used.sum()), rms_before=rms_before, rms_after=float("nan"), **refused,
                            reason=f"correction of {shift:.2f} m / {turn:.2f} deg exceeds {max_offset_m} m / {max_yaw_deg} deg")
    return MapAlignment(float(params[0]), float(params[1]), float(params[2]), (float(pivot[0]), float(pivot[1])),
                        int(used.sum()), rms_before, _rms(dist_after[dist_after <= gate_m]), True)


def _moved(local: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Points (N, 2) relative to the pivot, rotated by params[2] and shifted by params[:2]."""
    c, s = np.cos(params[2]), np.sin(params[2])
    return local @ np.array([[c, s], [-s, c]]) + params[:2]


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if len(values) else float("nan")
