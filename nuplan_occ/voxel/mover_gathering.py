"""An unboxed mover gathered over neighbouring frames: the flagged points of the output frames around one,
moved by the mover's own motion onto where it is in that frame.

One sweep's returns off a mover that has no box hit a fraction of the voxels its surface occupies; the
sweeps before and after hit others, as the object moves through the beams. Its motion is read from its
points, by how well two frames' points overlay: the overlap of their occupancy on a lattice of `cell_m` in
x-y per height layer of `layer_m` (`overlap_map`: the cross-correlation of the two, over every x-y shift).
- Velocity: one neighbour frame alone is ambiguous where the mover shows a flat side along its motion (the
  side slides onto itself). So the velocity (per output frame) is the one whose constant motion overlays the
  `velocity_frames` nearest frames before and after best on average (`joint_velocity`), at most `step_m` per
  frame.
- Chain: then outward in each direction, frame by frame, the shift is searched within `tolerance_m` of
  where the motion so far puts the frame, and at turns of `yaw_step_rad` either side of its turn so far (about
  the centre of the frame's points), ties going to the shift nearest the motion so far and to the turn so far
  (a part seen in both frames may slide inside a larger view of the object); the frame is gathered when the
  best overlap covers at least `min_overlap` of the smaller occupancy, and its points join the reference for
  the next frame. The first frame that fails ends that direction (the mover left, stopped being flagged, or
  is hidden).
A neighbour frame's candidates are its clusters of flagged points (points at most one voxel apart) that come
within `reach_m` of the gathered points where the motion puts them: whole clusters, as parts of the mover seen
only then belong to it. Once placed, only its points within `reach_m` of the frame's own points join, and
along the motion only those within the own points' span: another mover close behind or ahead can share a
cluster with it and would otherwise creep in frame by frame, and a shift read a little off along the motion
(the direction a side constrains least) would leave a trail where the mover was. Last, a placed point stays only
where a point of another frame, or of the frame's own, lies within one voxel of it (`supported`): once placed, a
surface recurs across the frames, while a stray return (a floater in the air, a ghost) that was flagged near the
mover in one frame does not, and would widen the mover's outline.

Frames: every point array is in one frame (the ego frame of the frame gathered onto), metres; z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter
from scipy.signal import fftconvolve

from nuplan_occ.points.knn import KdTree
from nuplan_occ.voxel.voxel_clusters import chebyshev_clusters


TIE_OVERLAP = 0.02
"""Overlaps this close to the best are ties (`OverlapMap.best_within`)."""


@dataclass(frozen=True)
class GatherSettings:
    """step_m: the farthest the mover moves from one output frame to the next (m); tolerance_m: how far a
    frame's shift may stray from the motion so far (m); yaw_step_rad: the turn tried either side of the turn
    so far, per frame (rad; 0: none); min_overlap: the share of the smaller occupancy that must overlay to
    gather a frame; reach_m: how near a neighbour's cluster must come to the gathered points to join (m);
    velocity_frames: frames on each side that tell the velocity; cell_m, layer_m: the occupancy lattice's x-y
    cell and height layer (m)."""

    step_m: float = 2.5
    tolerance_m: float = 0.3
    yaw_step_rad: float = np.deg2rad(3.0)
    min_overlap: float = 0.3
    reach_m: float = 1.0
    velocity_frames: int = 2
    cell_m: float = 0.1
    layer_m: float = 0.25


@dataclass(frozen=True)
class OverlapMap:
    """overlap (U, V): the share of the smaller occupancy that overlays when the moving points are shifted by
    origin + (u, v) * cell_m (x-y, m)."""

    overlap: np.ndarray
    origin: np.ndarray
    cell_m: float

    def at(self, shifts: np.ndarray) -> np.ndarray:
        """The overlap at x-y shifts (..., 2) m (the nearest lattice shift; 0 outside the map)."""
        ij = np.rint((np.asarray(shifts, dtype=np.float64)[..., :2] - self.origin) / self.cell_m).astype(np.int64)
        inside = (ij >= 0).all(axis=-1) & (ij[..., 0] < self.overlap.shape[0]) & (ij[..., 1] < self.overlap.shape[1])
        out = np.zeros(ij.shape[:-1])
        out[inside] = self.overlap[ij[inside][:, 0], ij[inside][:, 1]]
        return out

    def best_within(self, centre: np.ndarray, radius_m: float, tie: float = TIE_OVERLAP) -> tuple[np.ndarray, float]:
        """(shift (2,) m, overlap) of the best lattice shift within radius_m of centre (2,) m: of the shifts whose
        overlap is within `tie` of the best, the nearest to centre (a part seen in both frames can slide inside
        a larger view of the object; the motion so far decides); (centre, 0.0) when no lattice shift is that
        near."""
        u, v = np.meshgrid(np.arange(self.overlap.shape[0]), np.arange(self.overlap.shape[1]), indexing="ij")
        shifts = self.origin + np.stack([u, v], axis=-1) * self.cell_m
        distance = np.hypot(*(shifts - np.asarray(centre, dtype=np.float64)[:2]).transpose(2, 0, 1))
        near = distance <= radius_m + 1e-9
        if not near.any():
            return np.asarray(centre, dtype=np.float64)[:2], 0.0
        best = float(self.overlap[near].max())
        tied = near & (self.overlap >= best - tie)
        pick = np.unravel_index(int(np.argmin(np.where(tied, distance, np.inf))), distance.shape)
        return shifts[pick], float(self.overlap[pick])


def overlap_map(reference: np.ndarray, moving: np.ndarray, cell_m: float, layer_m: float) -> OverlapMap:
    """The overlap of the occupancy of `moving` (N, 3) shifted in x-y with that of `reference` (M, 3), over
    every shift at which they touch (module doc); both non-empty."""
    base = np.floor(min(reference[:, 2].min(), moving[:, 2].min()) / layer_m)
    layers = int(np.floor(max(reference[:, 2].max(), moving[:, 2].max()) / layer_m) - base) + 1

    def occupancy(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lower = points[:, :2].min(axis=0) - cell_m
        ij = np.floor((points[:, :2] - lower) / cell_m).astype(np.int64)
        k = (np.floor(points[:, 2] / layer_m) - base).astype(np.int64)
        grid = np.zeros((*(ij.max(axis=0) + 2), layers), dtype=np.float32)
        grid[ij[:, 0], ij[:, 1], k] = 1.0
        return grid, lower

    ref, ref_lower = occupancy(np.asarray(reference, dtype=np.float64))
    mov, mov_lower = occupancy(np.asarray(moving, dtype=np.float64))
    overlay = fftconvolve(ref, mov[::-1, ::-1, :], mode="full", axes=(0, 1)).sum(axis=2)
    overlay /= max(1.0, min(float(ref.sum()), float(mov.sum())))
    origin = ref_lower - mov_lower - (np.array(mov.shape[:2]) - 1) * cell_m
    return OverlapMap(overlay, origin, cell_m)


def joint_velocity(reference: np.ndarray, neighbours: dict[int, np.ndarray], settings: GatherSettings
                   ) -> np.ndarray | None:
    """(2,) m per output frame: the constant x-y velocity whose motion overlays the neighbours (signed frame
    step -> (N, 3) points) onto `reference` best on average (a frame k steps later is shifted by -k times the
    velocity), on a lattice of half cell_m per frame up to step_m; None without neighbour points."""
    maps = {step: overlap_map(reference, points, settings.cell_m, settings.layer_m)
            for step, points in neighbours.items() if len(points)}
    if not maps:
        return None
    axis = np.arange(-settings.step_m, settings.step_m + 1e-9, settings.cell_m / 2)
    velocities = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1)
    score = sum(m.at(-velocities * step) for step, m in maps.items()) / len(maps)
    score[np.hypot(velocities[..., 0], velocities[..., 1]) > settings.step_m + 1e-9] = -1.0
    return velocities[np.unravel_index(int(np.argmax(score)), score.shape)]


def near_clusters(points: np.ndarray, gathered: np.ndarray, shift: np.ndarray, reach_m: float, voxel_m: float
                  ) -> np.ndarray:
    """The points (N, 3) of the clusters (points at most one voxel of voxel_m apart, transitively) with a point
    within reach_m (x-y) of the gathered points (M, 3) once shifted by shift (2,) m."""
    near = _within(points, gathered, shift, reach_m)
    if not near.any():
        return points[:0]
    keys, point_key = np.unique(np.floor(points / voxel_m).astype(np.int64), axis=0, return_inverse=True)
    key_cluster, _ = chebyshev_clusters(keys, 3)
    cluster = key_cluster[point_key.reshape(-1)]
    return points[np.isin(cluster, np.unique(cluster[near]))]


def _within(points: np.ndarray, gathered: np.ndarray, shift: np.ndarray, reach_m: float) -> np.ndarray:
    """(N,) bool: the points (N, 3), shifted by shift (2,) m, within reach_m (x-y) of one of gathered (M, 3)."""
    if not len(points) or not len(gathered):
        return np.zeros(len(points), dtype=bool)
    tree = KdTree(np.c_[gathered[:, :2], np.zeros(len(gathered))])
    distance, _ = tree.query(np.c_[points[:, :2] + shift[:2], np.zeros(len(points))], 1, reach_m)
    return np.isfinite(distance[:, 0])


def _turned(points: np.ndarray, yaw: float) -> np.ndarray:
    """points (N, 3) turned by yaw (rad) about the vertical through their mean."""
    centre = points.mean(axis=0)
    c, s = np.cos(yaw), np.sin(yaw)
    out = points - centre
    out[:, :2] = out[:, :2] @ np.array([[c, s], [-s, c]])
    return out + centre


def gather_mover(own: np.ndarray, neighbours: dict[int, np.ndarray], settings: GatherSettings, voxel_m: float
                 ) -> np.ndarray:
    """(M, 3) the mover's own points (N, 3) and the points of the neighbour frames (signed output frame step
    -> that frame's flagged points (K, 3)) gathered onto them (module doc); voxel_m: the grid's voxel edge (m),
    which links a neighbour's clusters."""
    own = np.asarray(own, dtype=np.float64).reshape(-1, 3)
    if not len(own):
        return own
    nearest = {step: points[_within(points, own, np.zeros(2), settings.step_m * abs(step) + settings.reach_m)]
               for step, points in neighbours.items() if 0 < abs(step) <= settings.velocity_frames}
    velocity = joint_velocity(own, nearest, settings)
    if velocity is None:
        return own
    gathered = [own]
    for direction in (-1, 1):
        reference, per_step, turn = own, -velocity * direction, 0.0
        k = 0
        while direction * (k + 1) in neighbours:  # contiguous frames outward
            k += 1
            predicted = per_step * k
            candidates = near_clusters(neighbours[direction * k], reference, predicted, settings.reach_m, voxel_m)
            if not len(candidates):
                break
            best = (predicted, -1.0, 0.0, candidates)
            for dyaw in (0.0, -settings.yaw_step_rad, settings.yaw_step_rad) if settings.yaw_step_rad else (0.0,):
                yaw = turn * k + dyaw
                moved = _turned(candidates, yaw) if yaw else candidates
                shift, overlap = overlap_map(reference, moved + np.r_[predicted, 0.0], settings.cell_m,
                                             settings.layer_m).best_within(np.zeros(2), settings.tolerance_m)
                if overlap > best[1] + 1e-9:
                    best = (predicted + shift, overlap, yaw, moved)
            shift, overlap, yaw, moved = best
            if overlap < settings.min_overlap:
                break
            placed = moved + np.r_[shift, 0.0]
            placed = placed[_within(placed, own, np.zeros(2), settings.reach_m)]
            gathered.append(placed)
            reference = np.vstack([reference, placed])
            per_step, turn = shift / k, yaw / k
    return _within_own_span(supported(gathered, voxel_m), own, velocity)


def supported(parts: list[np.ndarray], cell_m: float) -> np.ndarray:
    """(M, 3) the points of parts[0] (the frame's own points) and those of every other part (one neighbour frame's
    placed points, (K, 3) each) that lie within one cell (Chebyshev, on a lattice of cells of cell_m, m) of a point
    of another part."""
    if len(parts) < 2:
        return parts[0]
    points = np.vstack(parts)
    part = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    cell = np.floor(points / cell_m).astype(np.int64)
    cell -= cell.min(axis=0) - 1  # a free cell on every side, so the neighbourhoods stay inside the lattice
    near = np.zeros((len(parts), *(cell.max(axis=0) + 2)), dtype=np.uint8)
    near[part, cell[:, 0], cell[:, 1], cell[:, 2]] = 1
    near = maximum_filter(near, size=(1, 3, 3, 3), mode="constant")
    at = (cell[:, 0], cell[:, 1], cell[:, 2])
    others_near = near.sum(axis=0, dtype=np.int64)[at] - near[(part, *at)]
    return points[(part == 0) | (others_near >= 1)]


def _within_own_span(points: np.ndarray, own: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """The points (N, 3) whose position along the motion (velocity (2,), per frame) lies within the own points'
    span along it: a mover ends, along the way it moves, where its own points end (all points when it did not
    move)."""
    speed = float(np.hypot(*velocity[:2]))
    if speed < 1e-9:
        return points
    along = points[:, :2] @ (velocity[:2] / speed)
    own_along = own[:, :2] @ (velocity[:2] / speed)
    return points[(along >= own_along.min() - 1e-9) & (along <= own_along.max() + 1e-9)]
