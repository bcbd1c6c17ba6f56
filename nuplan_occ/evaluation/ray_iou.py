"""RayIoU as SparseOcc defines it, at our grid's resolution: virtual LiDAR rays cast into the truth and the
prediction, scored by the class and depth of the first occupied voxel each ray meets.

Ray pattern (`ray_directions`): 360 azimuths, 0 to 359 degrees in steps of 1 degree, times 39 elevations:
-(90 deg - atan(k)) for k = 1 .. 10 (-45, -26.57, -18.43, ..., -5.71 deg), then on upward in the last of
those steps (atan(10) - atan(9) = 0.63 deg) until an elevation of at least 0.21 rad (12.03 deg) is reached
(last one 12.55 deg): 14,040 directions, denser near the horizon like a spinning LiDAR. SparseOcc built
the same pattern for the nuScenes LiDAR's field of view; it is kept unchanged so figures compare.

Origins (`ray_origins`): the LiDAR position of the scored frame and of the other frames of its scene, in
the scored frame's ego frame: each frame's T_global_from_ego applied to SENSOR_ORIGIN_EGO. Origins
within BORDER_MARGIN_M of the grid's x / y border or outside it are dropped (SparseOcc keeps |x|, |y| < 39 m
on its +-40 m grid); of the rest, the frame's own origin is always kept, plus up to MAX_ORIGINS - 1 of the
others evenly spaced in time (SparseOcc picks 8 evenly spaced among all, which may drop the frame's own).
A frame whose scene poses are unknown (NaN) is scored from its own origin only.

Casting (`cast_rays`): every ray from every origin is walked through the grid by the project's compiled
traversal (`nuplan_occ.rays.traversal`) to its first occupied voxel (label != 0). Its depth is the
distance from the origin to where the ray enters that voxel (SparseOcc takes where it leaves it; both
grids are measured the same way, so depth errors differ by at most the chord of one voxel). A ray that
leaves the grid without meeting an occupied voxel has label 0 (free) and no depth.

Scoring (`ray_counts`, `ray_iou`): rays whose truth label is free are dropped. For the rest, per class c
and threshold t: truth_c = rays whose truth label is c, pred_c = rays whose predicted label is c, tp_c =
rays with both labels c and |depth_pred - depth_truth| < t. Counts are summed over origins and frames
and IoU_c(t) = tp_c / (truth_c + pred_c - tp_c), NaN where that is 0/0 (class in neither). RayIoU@t is
the mean of the finite IoU_c(t) over the non-free classes; RayIoU is the mean of RayIoU@1, @2, @4 m.
No observability mask is applied: the rays decide what is seen. Units: metres; frames: the grid's ego frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import EMPTY
from nuplan_occ.rays.traversal import _segment, _voxel, grid_args, mark_visible_to_first_hit

THRESHOLDS_M = (1.0, 2.0, 4.0)
"""Depth tolerances of a true positive ray (SparseOcc's), metres."""

SENSOR_ORIGIN_EGO = np.array([1.5185, 0.0, 1.6309])
"""Where rays start in a frame's ego frame (m): the nominal translation of nuPlan's MergedPointCloud LiDAR
(ahead of and above the rear axle; the synthetic logs use the same extrinsic). Datasets do not store it."""

MAX_ORIGINS = 8
"""Origins per scored frame at most (SparseOcc's number)."""

BORDER_MARGIN_M = 1.0
"""Origins closer than this to the grid's x / y border are not used (SparseOcc's margin)."""

FIRST_ELEVATIONS = 10
"""Elevations -(90 deg - atan(k)), k = 1 .. FIRST_ELEVATIONS, before the even steps."""

TOP_ELEVATION_RAD = 0.21
"""The even elevation steps continue until one reaches this (the top of nuScenes' LiDAR field of view)."""

N_IDS = 256


def ray_elevations() -> np.ndarray:
    """The pattern's elevations (radians, ascending): see the module docstring."""
    elevations = [-(np.pi / 2 - np.arctan(k)) for k in range(1, FIRST_ELEVATIONS + 1)]
    step = elevations[-1] - elevations[-2]
    while elevations[-1] < TOP_ELEVATION_RAD:
        elevations.append(elevations[-1] + step)
    return np.asarray(elevations)


def ray_directions() -> np.ndarray:
    """(14040, 3) unit ray directions of the pattern (module docstring), elevation-major."""
    elevation = ray_elevations()[:, None]
    azimuth = np.radians(np.arange(360.0))[None, :]
    dirs = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                     np.broadcast_to(np.sin(elevation), (elevation.size, azimuth.size))], axis=-1)
    return dirs.reshape(-1, 3)


def ray_origins(poses: np.ndarray, index: int, grid: GridSpec,
                sensor_origin_ego: np.ndarray = SENSOR_ORIGIN_EGO) -> np.ndarray:
    """(K, 3) ray origins of frame `index` in its ego frame (m), K <= MAX_ORIGINS, its own first.

    poses: (F, 4, 4) T_global_from_ego of the frames of its scene in time order (NaN where unknown);
    sensor_origin_ego: (3,) the LiDAR position in every frame's ego frame. Selection: module docstring.
    """
    poses = np.asarray(poses, dtype=np.float64)
    own = np.asarray(sensor_origin_ego, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(poses[index])):
        return own[None].copy()
    relative = np.linalg.solve(poses[index][None], poses)  # T_ref_from_frame, (F, 4, 4)
    origins = relative[:, :3, :3] @ own + relative[:, :3, 3]
    lo, hi = grid.lower[:2] + BORDER_MARGIN_M, grid.upper[:2] - BORDER_MARGIN_M
    inside = np.all(np.isfinite(origins), axis=1) & np.all((origins[:, :2] > lo) & (origins[:, :2] < hi), axis=1)
    inside[index] = False
    others = origins[inside]
    if len(others) > MAX_ORIGINS - 1:
        others = others[np.unique(np.round(np.linspace(0, len(others) - 1, MAX_ORIGINS - 1)).astype(np.int64))]
    return np.concatenate([own[None], others])


@numba.njit(cache=True)
def _entry_voxels(starts, ends, stop_t, lower, voxel_size, shape, out):
    """out[r] = flat index of the voxel segment r enters at stop_t[r] (as the traversal evaluates entries;
    -1 outside the grid or for a segment that misses it)."""
    fx, fy, fz = float(shape[0]), float(shape[1]), float(shape[2])
    for r in range(starts.shape[0]):
        meets, ox, oy, oz, dx, dy, dz, t0, t1, inv = _segment(starts, ends, r, lower, voxel_size, shape)
        out[r] = _voxel(ox, oy, oz, dx, dy, dz, stop_t[r], inv, fx, fy, fz, shape[1], shape[2]) if meets else -1


def cast_rays(semantics: np.ndarray, origins: np.ndarray, directions: np.ndarray,
              grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """First occupied voxel along every ray: (labels (K * R,) uint8, depths (K * R,) float64 m).

    semantics: uint8 (X, Y, Z) of `grid`, 0 = free; origins (K, 3) m and directions (R, 3) unit vectors in
    the grid's ego frame; rays ordered origin-major. A ray meeting no occupied voxel gets label 0 and
    depth inf; depth is measured to where the ray enters its first occupied voxel.
    """
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    lower, voxel_size, shape = grid_args(grid)
    flat = np.ascontiguousarray(semantics).reshape(-1)
    occupied = flat != EMPTY
    # long enough to leave the grid from any origin: beyond its farthest corner
    length = float(np.max(np.linalg.norm(np.maximum(np.abs(origins - grid.lower), np.abs(origins - grid.upper)),
                                         axis=1))) + 1.0
    starts = np.repeat(origins, len(directions), axis=0)
    ends = starts + np.tile(directions, (len(origins), 1)) * length
    n = len(starts)
    stop_t, reached = np.zeros(n), np.zeros(n, dtype=bool)
    mark_visible_to_first_hit(starts, ends, lower, voxel_size, shape, occupied, 0.0, np.zeros(n),
                              np.zeros(occupied.size, dtype=bool), reached, stop_t)
    voxels = np.empty(n, dtype=np.int64)
    _entry_voxels(starts, ends, stop_t, lower, voxel_size, shape, voxels)
    hit = voxels >= 0
    hit[hit] = occupied[voxels[hit]]
    labels = np.zeros(n, dtype=np.uint8)
    labels[hit] = flat[voxels[hit]]
    depths = np.full(n, np.inf)
    depths[hit] = stop_t[hit] * length
    return labels, depths


@dataclass
class RayCounts:
    """Ray counts summed over origins and frames: truth[c], pred[c] (N_IDS,) int64 and tp[j, c]
    (len(thresholds), N_IDS) int64 at thresholds[j] metres (module docstring)."""

    thresholds: tuple[float, ...]
    truth: np.ndarray
    pred: np.ndarray
    tp: np.ndarray

    @classmethod
    def zeros(cls, thresholds: tuple[float, ...] = THRESHOLDS_M) -> "RayCounts":
        return cls(tuple(thresholds), np.zeros(N_IDS, np.int64), np.zeros(N_IDS, np.int64),
                   np.zeros((len(thresholds), N_IDS), np.int64))

    def __add__(self, other: "RayCounts") -> "RayCounts":
        return RayCounts(self.thresholds, self.truth + other.truth, self.pred + other.pred, self.tp + other.tp)


def ray_counts(pred_labels: np.ndarray, pred_depths: np.ndarray, truth_labels: np.ndarray,
               truth_depths: np.ndarray, thresholds: tuple[float, ...] = THRESHOLDS_M) -> RayCounts:
    """Counts of one set of rays cast into prediction and truth (`cast_rays` outputs, same rays in the
    same order); rays whose truth label is free are dropped (module docstring)."""
    keep = np.asarray(truth_labels) != EMPTY
    t_lab, p_lab = np.asarray(truth_labels)[keep].astype(np.int64), np.asarray(pred_labels)[keep].astype(np.int64)
    error = np.abs(np.asarray(pred_depths)[keep] - np.asarray(truth_depths)[keep])  # inf where pred hit nothing
    same = t_lab == p_lab
    tp = np.stack([np.bincount(t_lab[same & (error < t)], minlength=N_IDS) for t in thresholds]) \
        if thresholds else np.zeros((0, N_IDS), np.int64)
    return RayCounts(tuple(thresholds), np.bincount(t_lab, minlength=N_IDS), np.bincount(p_lab, minlength=N_IDS), tp)


def ray_iou(counts: RayCounts, class_ids: list[int]) -> dict:
    """RayIoU figures of summed counts over the non-free `class_ids` (module docstring).

    Returns {"per_class": {threshold: {id: IoU or NaN}}, "miou": {threshold: RayIoU@threshold},
    "rayiou": mean of the thresholds' RayIoU, "n_rays": rays scored (truth not free)}.
    """
    ids = [int(c) for c in class_ids if c != EMPTY]
    per_class, means = {}, {}
    for j, threshold in enumerate(counts.thresholds):
        scores = {}
        for c in ids:
            union = int(counts.truth[c] + counts.pred[c] - counts.tp[j, c])
            scores[c] = float(counts.tp[j, c] / union) if union else float("nan")
        finite = [v for v in scores.values() if np.isfinite(v)]
        per_class[threshold], means[threshold] = scores, float(np.mean(finite)) if finite else float("nan")
    finite_means = [v for v in means.values() if np.isfinite(v)]
    return {"per_class": per_class, "miou": means,
            "rayiou": float(np.mean(finite_means)) if finite_means else float("nan"),
            "n_rays": int(counts.truth.sum())}
