"""Observed-voxel masks by exact ray traversal of the grid (LiDAR rays and camera rays). Pure numpy.

Ray traversal (exact, vectorized, chunked): a segment from a to b (ego metres) is clipped to the grid
box; in voxel units the voxels it passes through are the voxel at its (clipped) start plus, for every
lattice plane it crosses, the voxel it enters there, found by evaluating the segment a hair (1e-6
voxel) after the crossing. All crossings of all rays of a chunk (ENTRY_CHUNK crossings, sized to stay
in cache) are generated at once (ragged arange), so there is no per-step Python loop. Slivers shorter
than 1e-6 voxel may be skipped. Per-ray values are expanded with np.repeat (rays are contiguous) and
the index along the crossed axis follows from the plane index (exactly, see _EXACT_NUDGE), so only
the two other axes are evaluated in floating point.

LiDAR (mask_lidar): the voxels strictly before the return point are observed free, the voxel holding
the return is observed occupied; the mask is free | occupied, the rest unknown.

Camera (mask_camera): pinhole model with the calibration's K (lens distortion ignored: the frustum is
that of the undistorted image), OpenCV camera axes (x right, y down, z forward) for T_ego_from_camera.
Rays are cast through a sub-sampled pixel lattice whose angular step is `voxel_size / max_range_m`
(adjacent rays are at most one voxel apart at max range); along each ray the voxels up to and including
the first occupied one (and within max_range_m) are visible. Occupied voxels closer than `near_m` to the
camera (its own vehicle) do not occlude. Rays are marched window by window along their length
(WINDOW_EDGES_VOXELS) and a ray is dropped once its first occupied voxel is found, so the voxels
behind an obstacle are never generated; the result is that of traversing every ray to its end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import CameraCalibration

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
"""Values of `lidar_observation`."""

ENTRY_CHUNK = 250_000
"""Ray/voxel entries generated at once (bounds temporary memory)."""

_NUDGE = 1e-6


class VisibilityError(ValueError):
    """Malformed rays, points or camera calibration."""


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise VisibilityError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    return p


def _clip_to_box(o: np.ndarray, d: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter range [t0, t1] within [0, 1] of segments o + t d (voxel units) inside [0, shape]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (0.0 - o) / d
        tb = (shape - o) / d
    t_lo = np.where(d == 0, np.where((o >= 0) & (o < shape), -np.inf, np.inf), np.minimum(ta, tb))
    t_hi = np.where(d == 0, np.where((o >= 0) & (o < shape), np.inf, -np.inf), np.maximum(ta, tb))
    return np.maximum(t_lo.max(axis=1), 0.0), np.minimum(t_hi.min(axis=1), 1.0)


@dataclass
class _Segments:
    """Segments o + t d, t in [t0, t1) (the part inside the grid box), in voxel units, stored by axis:
    o, d (3, N); planes crossed per axis are first .. last (none where d is 0); inv_len = nudge / |d|;
    index: the segment's index in the caller's input."""

    o: np.ndarray
    d: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    first: np.ndarray
    last: np.ndarray
    inv_len: np.ndarray
    index: np.ndarray


def _segments(starts_ego: np.ndarray, ends_ego: np.ndarray, grid: GridSpec) -> _Segments:
    """The segments start -> end (N, 3) metres in the ego frame that meet the grid box."""
    shape = np.asarray(grid.shape, dtype=np.float64)
    o = (starts_ego - grid.lower) / grid.voxel_size
    d = (ends_ego - grid.lower) / grid.voxel_size - o
    t0, t1 = _clip_to_box(o, d, shape)
    rays = np.flatnonzero(t0 < t1)
    o, d, t0, t1 = o[rays], d[rays], t0[rays], t1[rays]
    a, b = o + t0[:, None] * d, o + t1[:, None] * d
    first = np.floor(np.minimum(a, b)).astype(np.int64) + 1
    last = np.where(d == 0, first - 1, np.floor(np.maximum(a, b)).astype(np.int64))
    inv_len = _NUDGE / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    return _Segments(np.ascontiguousarray(o.T), np.ascontiguousarray(d.T), t0, t1, np.ascontiguousarray(first.T),
                     np.ascontiguousarray(last.T), inv_len, rays)


_EXACT_NUDGE = 1e-12
"""Through plane k of an axis, o + (t + inv_len) d (t = (k - o) / d, that axis) is k + inv_len d up to a
rounding error below ~1.4e-15 (1 + 2|o| + |d|). Where the nudge |d| inv_len exceeds _EXACT_NUDGE times
(1 + 2|o| + |d|) (a ~700x margin), its floor is therefore k (d > 0) or k - 1 (d < 0) exactly; the few
entries of rays nearly parallel to the planes are evaluated in floating point instead."""


def _entries(s: _Segments, sel: np.ndarray, t_min: float, t_max: float, shape: tuple[int, int, int]):
    """Voxels entered by segments `sel` with entry parameter t in [t_min, min(t_max, t1)): the start voxel
    (entered at t0) and, per lattice plane crossed, the voxel entered there, i.e. the voxel holding
    o + (t + inv_len) d. Returns (segment ids, flat voxel index (C order), t) of the entries inside the
    grid, in no particular order."""
    o, d, inv = s.o[:, sel], s.d[:, sel], s.inv_len[sel]
    t0, t_end = s.t0[sel], np.minimum(s.t1[sel], t_max)
    lo_t = np.maximum(t0, t_min)
    parts = []
    starting = (t0 >= t_min) & (t0 < t_max)
    if starting.any():
        parts.append(_voxels_of(sel, starting.astype(np.int64), o, d, inv, t0[starting], None, None, shape))
    for axis in range(3):
        a, b = o[axis] + lo_t * d[axis], o[axis] + t_end * d[axis]
        lo = np.maximum(np.floor(np.minimum(a, b)).astype(np.int64), s.first[axis, sel])
        hi = np.minimum(np.floor(np.maximum(a, b)).astype(np.int64) + 1, s.last[axis, sel])
        n = np.maximum(hi - lo + 1, 0)
        k = np.repeat(lo - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))
        t = (k - np.repeat(o[axis], n)) / np.repeat(d[axis], n)
        keep = t < np.repeat(t_end, n)
        if t_min > -np.inf:
            keep &= t >= t_min
        parts.append(_voxels_of(sel, n, o, d, inv, t, (axis, k), keep, shape))
    ids, flat, t = (np.concatenate(p) for p in zip(*parts))
    return ids, flat, t


def _voxels_of(sel, n, o, d, inv, t, crossing, keep, shape):
    """(segment ids, flat voxel index, t) of the entries at t of segments sel (n entries each, in order),
    kept where `keep` (None: all) and inside the grid. crossing = (axis, plane index k) when the entries
    cross planes of that axis (the voxel index along it then follows from k), else None."""
    step = t + np.repeat(inv, n)
    inside = np.ones(len(t), dtype=bool) if keep is None else keep
    flat = np.zeros(len(t), dtype=np.int64)
    for axis in range(3):
        d_r = np.repeat(d[axis], n)
        if crossing is not None and crossing[0] == axis:
            v = crossing[1] - (d_r < 0)
            tiny = np.abs(d[axis]) * inv <= _EXACT_NUDGE * (1.0 + 2.0 * np.abs(o[axis]) + np.abs(d[axis]))
            if tiny.any():
                fix = np.flatnonzero(np.repeat(tiny, n))
                v[fix] = np.floor(np.repeat(o[axis], n)[fix] + step[fix] * d_r[fix]).astype(np.int64)
            inside &= (v >= 0) & (v < shape[axis])
        else:
            x = np.repeat(o[axis], n) + step * d_r
            inside &= (x >= 0) & (x < shape[axis])  # the same as for floor(x): shape is an integer
            v = x.astype(np.int64)  # truncation = floor where inside
        flat *= shape[axis]
        flat += v
    return np.repeat(sel, n)[inside], flat[inside], t[inside]


def _chunks(s: _Segments, sel: np.ndarray, t_min: float, t_max: float):
    """Split segments `sel` into runs of about ENTRY_CHUNK plane crossings within [t_min, t_max)."""
    if len(sel) == 0:
        return
    span = (np.minimum(s.t1[sel], t_max) - np.maximum(s.t0[sel], t_min)).clip(0.0)
    cum = np.cumsum(np.abs(s.d[:, sel]).sum(axis=0) * span + 4.0)
    cuts = np.searchsorted(cum, np.arange(ENTRY_CHUNK, cum[-1], ENTRY_CHUNK), side="right")
    edges = np.unique(np.concatenate([[0], cuts, [len(sel)]]))
    for start, stop in zip(edges[:-1], edges[1:]):
        yield sel[start:stop]


def traverse(starts_ego: np.ndarray, ends_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID):
    """Yield, chunk by chunk, the voxels segments pass through: (ray index (global), flat voxel index in
    the grid (C order), entry parameter t in [0, 1)). starts/ends (N, 3) metres in the ego frame."""
    s = _segments(starts_ego, ends_ego, grid)
    for sel in _chunks(s, np.arange(len(s.t0)), -np.inf, np.inf):
        ids, flat, t = _entries(s, sel, -np.inf, np.inf, grid.shape)
        yield s.index[ids], flat, t


def lidar_observation(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """uint8 (X, Y, Z): UNKNOWN 0, FREE 1 (a ray passed through before its return), OCCUPIED 2 (holds a
    return; wins over free). points_ego (N, 3) returns, origins_ego (N, 3) or (3,) ray origins, metres
    in the ego frame."""
    points = _as_points(points_ego, "lidar_observation points_ego")
    origins = np.broadcast_to(np.asarray(origins_ego, dtype=np.float64), points.shape)
    obs = np.zeros(int(np.prod(grid.shape)), dtype=np.uint8)
    for _, flat, _ in traverse(origins, points, grid):
        obs[flat] = FREE
    idx, inside = grid.point_to_index(points)
    idx = idx[inside]
    obs[(idx[:, 0] * grid.shape[1] + idx[:, 1]) * grid.shape[2] + idx[:, 2]] = OCCUPIED
    return obs.reshape(grid.shape)


def lidar_visibility(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z) mask_lidar: voxels observed (free or occupied) by the rays origin -> return point
    (points (N, 3), origins (N, 3) or (3,), metres in the ego frame)."""
    return lidar_observation(points_ego, origins_ego, grid) != UNKNOWN


def camera_rays(camera: CameraCalibration, angular_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (R, 3) in the ego frame of rays through a pixel lattice of the
    camera's image with about `angular_step_rad` between neighbours (pinhole, OpenCV axes)."""
    K = np.asarray(camera.K, dtype=np.float64)
    T = np.asarray(camera.T_ego_from_camera, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4) or K[0, 0] <= 0 or K[1, 1] <= 0 or camera.width <= 0 or camera.height <= 0:
        raise VisibilityError(f"camera {camera.channel}: invalid intrinsics/extrinsics/size")
    step_u = max(1.0, K[0, 0] * angular_step_rad)
    step_v = max(1.0, K[1, 1] * angular_step_rad)
    u = np.arange(step_u / 2.0, camera.width, step_u)
    v = np.arange(step_v / 2.0, camera.height, step_v)
    U, V = np.meshgrid(u, v, indexing="ij")
    x = (U.ravel() - K[0, 2] - K[0, 1] * (V.ravel() - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (V.ravel() - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=1)
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    return T[:3, 3].copy(), d_cam @ T[:3, :3].T


WINDOW_EDGES_VOXELS = (16, 40, 80, 160)
"""Distances (voxels along the ray) at which camera rays are marched in turn; a ray stops at the first
window holding its first occupied voxel, so later windows are never generated for it."""


def _window_edges(ray_length_voxels: float) -> list[tuple[float, float]]:
    """Consecutive [t_min, t_max) parameter windows covering (-inf, inf) for rays of the given length."""
    cuts = [e / ray_length_voxels for e in WINDOW_EDGES_VOXELS if e < ray_length_voxels]
    bounds = [-np.inf, *cuts, np.inf]
    return list(zip(bounds[:-1], bounds[1:]))


def camera_visibility(occupied: np.ndarray, cameras: list[CameraCalibration], grid: GridSpec = DEFAULT_GRID,
                      max_range_m: float = 60.0, angular_step_rad: float | None = None,
                      near_m: float = 0.5) -> np.ndarray:
    """bool (X, Y, Z) mask_camera: voxels some camera sees (see module doc). occupied: bool (X, Y, Z)
    occupancy in the ego frame; cameras: calibrations with T_ego_from_camera.

    Rays of all cameras are marched together window by window along their length (WINDOW_EDGES_VOXELS);
    a ray that met its first occupied voxel in a window is dropped from the later ones. Within a window
    the visible voxels of a ray are those entered no later than its first occupied one."""
    if tuple(occupied.shape) != tuple(grid.shape):
        raise VisibilityError(f"camera_visibility: occupied has shape {occupied.shape}, grid {grid.shape}")
    step = grid.voxel_size / max_range_m if angular_step_rad is None else angular_step_rad
    occ = np.asarray(occupied, dtype=bool).ravel()
    visible = np.zeros(occ.shape, dtype=bool)
    if not cameras:
        return visible.reshape(grid.shape)
    starts, ends = [], []
    for camera in cameras:
        origin, dirs = camera_rays(camera, step)
        starts.append(np.broadcast_to(origin, dirs.shape))
        ends.append(starts[-1] + dirs * max_range_m)
    s = _segments(np.concatenate(starts), np.concatenate(ends), grid)
    near_t = near_m / max_range_m
    t_hit = np.full(len(s.t0), np.inf)
    active = np.arange(len(s.t0))
    for t_min, t_max in _window_edges(max_range_m / grid.voxel_size):
        active = active[(s.t1[active] > t_min) & np.isinf(t_hit[active])]
        for sel in _chunks(s, active[s.t0[active] < t_max], t_min, t_max):
            ids, flat, t = _entries(s, sel, t_min, t_max, grid.shape)
            blocking = occ[flat] & (t >= near_t)
            np.minimum.at(t_hit, ids[blocking], t[blocking])
            visible[flat[t <= t_hit[ids]]] = True
    return visible.reshape(grid.shape)
