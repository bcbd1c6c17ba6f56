"""Solid object shapes by space carving in the object's BOX frame (origin at the box centre, x along the
heading, z up; metres).

The box [-size/2, size/2] is tiled by a lattice of cells of edge <= `resolution`. A cell is carved (free)
when a ray from a sensor origin to one of the object's points passes through it before reaching the point;
every other cell stays solid: cells holding a point (the observed surface) and cells no ray reached (the
unobserved inside). The result is the object's visual hull seen from the aggregated sensor poses, which
is closed by construction, so a voxelizer fills it solid where the surface itself is open.

The hull keeps every cell no ray reached, and nothing reaches the air above an object where the sky behind it
gives no return (above a truck's bed, beside its cab). `under_top_envelope` removes those cells: an object is
taken to have no overhang, so a cell higher than the highest point of the columns around it is air; a column with
no point of the object's body (only ground returns, or none) around it may take the top of its cross-section
(the seen columns across the box's width at its place along the length), then a low quantile of the tops of the
columns seen anywhere on the object (the end of a vehicle of which no return came at all is its bonnet or bed,
lower than its cabin, rather than the box's full height), else it is unknown and keeps its cells.
`within_side_reach` ends a solid where its points end across and along the box, symmetrically about its centre:
the box's room around its object, which no ray may have crossed on the object's hidden side, is not solid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from scipy import ndimage

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.box_cull import segments_near_box
from nuplan_occ.io.types import Boxes


@dataclass(frozen=True)
class SolidSamples:
    """A carved solid as points in the BOX frame (m): points (M, 3) sample the solid lattice cells (their
    centres, or their corners); observed (M,) bool: the sample's cell holds one of the object's points."""

    points: np.ndarray
    observed: np.ndarray


def lattice_shape(size: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """(counts (3,) int, cell edges (3,) m) of the lattice tiling a box of `size` (3,) m with cells of edge
    at most `resolution` m (at least one cell per axis)."""
    counts = np.maximum(np.ceil(np.asarray(size, np.float64) / resolution - 1e-9), 1).astype(np.int64)
    return counts, np.asarray(size, np.float64) / counts


def lattice_cells(xyz_box: np.ndarray, size: np.ndarray, edge: np.ndarray, counts: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(inside (N,) bool, flat C-order cell index of each inside point (K,)) of points xyz_box (N, 3, box
    frame) in the lattice (counts, edge) = `lattice_shape(size, ...)` of a box of `size`."""
    ijk = np.floor((np.asarray(xyz_box, np.float64).reshape(-1, 3) + np.asarray(size, np.float64) / 2.0) / edge).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < counts), axis=1)
    ijk = ijk[inside]
    return inside, (ijk[:, 0] * counts[1] + ijk[:, 1]) * counts[2] + ijk[:, 2]


def clip_segments_to_box(starts: np.ndarray, ends: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameters [t0, t1] of the parts of segments start + t (end - start), t in [0, 1], inside the box
    [-half, half] (slab method); segments missing the box come back with t0 > t1. starts, ends (N, 3)."""
    d = ends - starts
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (-half - starts) / d
        tb = (half - starts) / d
    parallel = np.abs(d) < 1e-12
    inside = np.abs(starts) <= half
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return np.maximum(lo.max(axis=1), 0.0), np.minimum(hi.min(axis=1), 1.0)


def segments_through_box(starts: np.ndarray, ends: np.ndarray, center: np.ndarray, yaw: float,
                         size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The segments start -> end (N, 3) (e.g. sensor origin -> background return, ego frame) that cross an
    upright box (center (3,), yaw rad, size (3,) [length, width, height] in the same frame), moved into the
    box frame: (starts_box (K, 3), ends_box (K, 3)), in input order. A compiled test picks the segments near
    the box (box_cull), the exact slab test of `clip_segments_to_box` decides among them."""
    starts, ends = np.asarray(starts, np.float64), np.asarray(ends, np.float64)
    center, half = np.asarray(center, np.float64), np.asarray(size, np.float64) / 2.0
    near = np.flatnonzero(segments_near_box(starts, ends, center, float(yaw), half, CULL_GROW_M))
    c, s = np.cos(yaw), np.sin(yaw)
    R_box_from_frame = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    starts_box = (starts[near] - center) @ R_box_from_frame.T
    ends_box = (ends[near] - center) @ R_box_from_frame.T
    t0, t1 = clip_segments_to_box(starts_box, ends_box, half)
    crossing = t0 < t1
    return starts_box[crossing], ends_box[crossing]


CULL_GROW_M = 1e-6
"""segments_through_box decides exactly only the segments crossing the box grown by this (box_cull)."""


def rays_through_boxes(backgrounds: Sequence[np.ndarray], boxes: Sequence[Boxes], sensor_origin_ego: np.ndarray,
                       tracks: set[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Track -> (starts (K, 3), ends (K, 3)) in its box frame (m): the rays sensor_origin_ego -> return of every
    sweep's background (backgrounds[i] (N_i, 3), ego frame; read only for a sweep boxing one of them) that cross
    the track's box in that sweep (boxes[i], Boxes of the same sweep), for the tracks in `tracks`; a track boxed
    in some sweep gets an entry (maybe empty), the others none."""
    through: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for i, sweep_boxes in enumerate(boxes):
        listed = [k for k, track in enumerate(sweep_boxes.track_tokens) if track in tracks]
        if not listed:
            continue
        points = backgrounds[i]
        origins = np.broadcast_to(sensor_origin_ego, points.shape)
        for k in listed:
            through.setdefault(sweep_boxes.track_tokens[k], []).append(segments_through_box(
                origins, points, sweep_boxes.centers[k], float(sweep_boxes.yaws[k]), sweep_boxes.sizes[k]))
    return {track: (np.vstack([r[0] for r in rays]), np.vstack([r[1] for r in rays])) for track, rays in through.items()}


def carve_object_solid(points_box: np.ndarray, origins_box: np.ndarray, size: np.ndarray, resolution: float = 0.1,
                       stop_before_m: float | None = None, min_rays: int = 1, chunk_samples: int = 2_000_000,
                       through: tuple[np.ndarray, np.ndarray] | None = None,
                       through_margin_m: float = 0.05) -> np.ndarray:
    """(M, 3) centres (box frame, m) of the lattice cells of the box that stay solid after space carving.

    points_box (N, 3): the object's points in its box frame (points outside the box are ignored as
    surface but their rays still carve the box); origins_box (N, 3): the sensor origin of each point in
    the same frame; size (3,) [length, width, height] m. Each ray is clipped to the box and sampled every
    resolution / 2 up to `stop_before_m` (default resolution / 2) before its point, so noise in depth does
    not carve the surface; a cell is carved when at least `min_rays` distinct rays have a sample in it and
    it holds no point. `through` = (starts (K, 3), ends (K, 3)), box frame: more rays that carve the same
    way but whose ends are not the object's (returns beyond the box, see `segments_through_box`); they carve
    only deeper than `through_margin_m` inside the box faces, since a noisy box puts the object's own edge
    where such a ray passed. `chunk_samples` bounds the memory of one batch of samples.
    """
    points = np.asarray(points_box, np.float64)
    origins = np.asarray(origins_box, np.float64)
    size = np.asarray(size, np.float64).reshape(-1)
    if points.ndim != 2 or points.shape[1] != 3 or origins.shape != points.shape:
        raise PointInputError(f"carve_object_solid: points_box (N, 3) and origins_box of the same shape required, "
                             f"got {points.shape} and {origins.shape}")
    if size.shape != (3,) or not np.all(size > 0) or not resolution > 0 or min_rays < 1:
        raise PointInputError(f"carve_object_solid: size must be 3 positive lengths, resolution > 0 and min_rays >= 1; "
                             f"got size {size}, resolution {resolution}, min_rays {min_rays}")
    counts, edge = lattice_shape(size, resolution)
    half = size / 2.0
    step = resolution / 2.0
    stop = step if stop_before_m is None else float(stop_before_m)

    n_cells = int(np.prod(counts))
    traversed = np.zeros(n_cells, np.int64)
    starts, ends = origins, points
    t0, t1 = clip_segments_to_box(origins, points, half)
    if through is not None:
        through_starts = np.asarray(through[0], np.float64).reshape(-1, 3)
        through_ends = np.asarray(through[1], np.float64).reshape(-1, 3)
        u0, u1 = clip_segments_to_box(through_starts, through_ends, np.maximum(half - through_margin_m, 0.0))
        starts, ends = np.vstack([origins, through_starts]), np.vstack([points, through_ends])
        t0, t1 = np.r_[t0, u0], np.r_[t1, u1]
    length = np.linalg.norm(ends - starts, axis=1)
    t1 = np.minimum(t1, 1.0 - stop / np.maximum(length, 1e-12))
    keep = (t1 >= t0) & (length > 0)
    rays_o, rays_d, t0, t1, length = starts[keep], (ends - starts)[keep], t0[keep], t1[keep], length[keep]
    samples = np.floor((t1 - t0) * length / step).astype(np.int64) + 1
    cumulative = np.cumsum(samples)
    total = int(cumulative[-1]) if len(samples) else 0
    cuts = np.searchsorted(cumulative, np.arange(chunk_samples, total, chunk_samples), side="right")
    splits = np.unique(np.r_[0, cuts, len(samples)])
    for start, end in zip(splits[:-1], splits[1:]):
        n = samples[start:end]
        owner = np.repeat(np.arange(start, end), n)
        offset = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        t = t0[owner] + offset * step / length[owner]
        ok, cells = lattice_cells(rays_o[owner] + t[:, None] * rays_d[owner], size, edge, counts)
        ray_cells = np.unique(owner[ok] * n_cells + cells) % n_cells
        traversed += np.bincount(ray_cells, minlength=n_cells)
    solid = traversed < min_rays
    solid[lattice_cells(points, size, edge, counts)[1]] = True
    ijk = np.stack(np.unravel_index(np.flatnonzero(solid), tuple(counts)), axis=1)
    return (ijk + 0.5) * edge - half


def cell_corner_points(cells_box: np.ndarray, size: np.ndarray, resolution: float, inset: float = 0.05) -> np.ndarray:
    """(8 M, 3) points near the 8 corners of each lattice cell (centres cells_box (M, 3), box frame, of the
    lattice `lattice_shape(size, resolution)`), moved inward by `inset` of a cell edge: voxelizing them
    marks every voxel a cell overlaps by more than that inset, where voxelizing the centres misses the
    voxels a cell only grazes."""
    _, edge = lattice_shape(size, resolution)
    signs = np.array(np.meshgrid([-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0], indexing="ij")).reshape(3, -1).T
    offsets = signs * (0.5 - inset) * edge
    return (np.asarray(cells_box, np.float64)[:, None, :] + offsets[None]).reshape(-1, 3)


def cells_holding_points(cells_box: np.ndarray, points_box: np.ndarray, size: np.ndarray, resolution: float) -> np.ndarray:
    """(M,) bool: the lattice cells (centres cells_box (M, 3), box frame, lattice `lattice_shape(size,
    resolution)`) that hold at least one of points_box (N, 3, box frame)."""
    counts, edge = lattice_shape(size, resolution)
    inside, cells = lattice_cells(cells_box, size, edge, counts)
    held = np.zeros(len(inside), dtype=bool)
    held[inside] = np.isin(cells, lattice_cells(points_box, size, edge, counts)[1])
    return held


def body_points(points_box: np.ndarray, size: np.ndarray, floor_clearance_m: float) -> np.ndarray:
    """(K, 3) the object's body: those of points_box (N, 3, box frame, m) more than floor_clearance_m above the
    bottom of a box of `size` (3,) (the points below are its ground)."""
    points = np.asarray(points_box, np.float64).reshape(-1, 3)
    return points[points[:, 2] > -np.asarray(size, np.float64)[2] / 2 + floor_clearance_m]


def under_top_envelope(cells_box: np.ndarray, points_box: np.ndarray, size: np.ndarray, resolution: float,
                       reach_m: float, pad_m: float, floor_clearance_m: float, across_width: bool = False,
                       unseen_quantile: float | None = None) -> np.ndarray:
    """(M,) bool: the lattice cells (centres cells_box (M, 3), box frame, lattice `lattice_shape(size,
    resolution)`) whose bottom lies at most pad_m above the highest of the object's body points (points_box
    (N, 3) inside the box and more than floor_clearance_m above its bottom) in the columns within reach_m (x and
    y) of theirs. A column with no such point within reach takes, with `across_width`, the highest point of its
    cross-section (every column across the box's width within reach_m along its length: a vehicle is about as
    tall across its width, so the unseen top of a hood or a bus's far end ends where its seen sides do), then with
    `unseen_quantile` (in [0, 1]) that quantile of the highest points of all the columns holding one (an end of
    which nothing was seen takes a low top of the seen ones: a bonnet's or a bed's, not the cabin's); cells of
    columns still without one are kept (True). Metres."""
    size = np.asarray(size, np.float64)
    counts, edge = lattice_shape(size, resolution)
    points = body_points(points_box, size, floor_clearance_m)
    inside, flat = lattice_cells(points, size, edge, counts)
    top = np.full(int(counts[0] * counts[1]), -np.inf)
    np.maximum.at(top, flat // counts[2], points[inside, 2])
    reach = int(np.ceil(reach_m / min(edge[0], edge[1]) - 1e-9))
    top = top.reshape(counts[0], counts[1])
    near = ndimage.maximum_filter(top, size=2 * reach + 1, mode="constant", cval=-np.inf)
    if across_width:
        section = ndimage.maximum_filter1d(top.max(axis=1), size=2 * reach + 1, mode="constant", cval=-np.inf)
        near = np.where(np.isneginf(near), section[:, None], near)
    seen_tops = top[~np.isneginf(top)]
    if unseen_quantile is not None and len(seen_tops):
        near = np.where(np.isneginf(near), np.quantile(seen_tops, unseen_quantile), near)
    top = near
    cells = np.asarray(cells_box, np.float64).reshape(-1, 3)
    column = np.floor((cells[:, :2] + size[:2] / 2) / edge[:2]).astype(np.int64)
    column = np.clip(column, 0, counts[:2] - 1)
    column_top = top[column[:, 0], column[:, 1]]
    return np.isneginf(column_top) | (cells[:, 2] - edge[2] / 2 <= column_top + pad_m)


def within_side_reach(cells_box: np.ndarray, points_box: np.ndarray, size: np.ndarray, resolution: float,
                      floor_clearance_m: float, quantile: float, min_points: int = 20) -> np.ndarray:
    """(M,) bool: the lattice cells (centres cells_box (M, 3), box frame, lattice `lattice_shape(size, resolution)`)
    that start within the `quantile` of the object's body points' |x| and |y| (points_box (N, 3) more than
    floor_clearance_m above the box's bottom): symmetric about the box centre, so a side no ray reached mirrors
    the seen one, and a box with room around its object (padded, or too large) draws none of it solid. Fewer
    than min_points body points: every cell (True). Metres."""
    size = np.asarray(size, np.float64)
    cells = np.asarray(cells_box, np.float64).reshape(-1, 3)
    body = body_points(points_box, size, floor_clearance_m)
    if len(body) < min_points:
        return np.ones(len(cells), dtype=bool)
    _, edge = lattice_shape(size, resolution)
    reach = np.quantile(np.abs(body[:, :2]), quantile, axis=0)
    return np.all(np.abs(cells[:, :2]) - edge[:2] / 2 <= reach, axis=1)


@dataclass(frozen=True)
class TopEnvelope:
    """The settings of `under_top_envelope` for a solid (m): reach_m, pad_m, floor_clearance_m, across_width,
    unseen_quantile; with side_quantile, the solid also ends `within_side_reach` of that quantile."""

    reach_m: float
    pad_m: float
    floor_clearance_m: float
    across_width: bool = False
    unseen_quantile: float | None = None
    side_quantile: float | None = None


def object_solid_samples(points_box: np.ndarray, origins_box: np.ndarray, size: np.ndarray, resolution: float,
                         through: tuple[np.ndarray, np.ndarray] | None, corners: bool,
                         envelope: TopEnvelope | None = None) -> SolidSamples:
    """An object's carved solid (`carve_object_solid` of its points_box (N, 3) seen from origins_box (N, 3), box
    of `size` (3,), cells of edge <= resolution, more carving rays `through`; all box frame, m), with `envelope`
    only its cells `under_top_envelope` (and `within_side_reach` with envelope.side_quantile), as samples: the
    solid cells' centres, or with `corners` the 8 points near each cell's corners (`cell_corner_points`, so the
    voxelizer marks every voxel a cell overlaps); each sample observed when its cell holds a point."""
    cells = carve_object_solid(points_box, origins_box, size, resolution=resolution, through=through)
    if envelope is not None:
        cells = cells[under_top_envelope(cells, points_box, size, resolution, envelope.reach_m, envelope.pad_m,
                                         envelope.floor_clearance_m, envelope.across_width,
                                         envelope.unseen_quantile)]
        if envelope.side_quantile is not None:
            cells = cells[within_side_reach(cells, points_box, size, resolution, envelope.floor_clearance_m,
                                            envelope.side_quantile)]
    observed = cells_holding_points(cells, points_box, size, resolution)
    if corners:
        return SolidSamples(cell_corner_points(cells, size, resolution), np.repeat(observed, 8))
    return SolidSamples(cells, observed)
