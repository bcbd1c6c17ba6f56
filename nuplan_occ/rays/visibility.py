"""Observed-voxel masks by exact ray traversal of the grid (LiDAR rays and camera rays).

Traversal: `nuplan_occ.rays.traversal` (the voxels a segment passes through, exactly, ray by ray in
compiled kernels; slivers shorter than 1e-6 voxel may be skipped).

LiDAR (mask_lidar): the voxels strictly before the return point are observed free, the voxel holding
the return is observed occupied (occupied wins over another ray's free); the mask is free | occupied,
the rest unknown.

Camera (mask_camera): pinhole model with the calibration's K (lens distortion ignored: the frustum is
that of the undistorted image), OpenCV camera axes (x right, y down, z forward) for T_ego_from_camera.
Along each ray the voxels up to and including the first occupied one (and within max_range_m) are
visible; occupied voxels closer than `near_m` to the camera (its own vehicle) do not occlude. Rays are
cast through sub-sampled pixel lattices, one per range band: the bands end at max_range_m / 2**k
(k = range_bands - 1, ..., 0) and begin where the previous one ends, and a band's lattice has the angular
step voxel_size / (its far end), so adjacent rays are at most one voxel apart anywhere in their band
(the nearest band's rays are 4**(range_bands - 1) times fewer than a max-range lattice's). A ray of a
band is a segment from its camera to the band's far end. Its parent is the previous band's ray whose
pixel cell holds its pixel; it is walked from the band's near end when the parent and the 8 rays around
the parent all reached their far end unblocked, and not at all when none of them did. Where they disagree
(an occluder's edge) it is walked from RESUME_MARGIN_VOXELS before the nearest point up to which those 9
rays are known unblocked: the least, over them, of where a walked ray's walk ended (its first occupied voxel,
the grid's border or its far end) and, for a ray not walked, that same least point of its own 9 parents.
Each ray is marched voxel by voxel and stops at its first occupied voxel, so the voxels behind an
obstacle are never visited. range_bands = 1 is the single max-range lattice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import CameraCalibration
from nuplan_occ.voxel.frame_lookup import point_voxels
from nuplan_occ.rays.traversal import grid_args, mark_bits, mark_traversed, mark_visible_to_first_hit

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
"""Values of `lidar_observation`."""
RESUME_MARGIN_VOXELS = 1.0
"""An edge ray is walked from this many voxels before the nearest point its parent rays walked to unblocked."""


class VisibilityError(ValueError):
    """Malformed rays, points or camera calibration."""


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise VisibilityError(f"{name}: expected (N, 3) points, got shape {p.shape}")
    return p


def lidar_observation_bits(points_ego: np.ndarray, origins_ego: np.ndarray,
                           grid: GridSpec = DEFAULT_GRID) -> tuple[np.ndarray, np.ndarray]:
    """(observed bits, FREE bits) of `lidar_observation`'s grid, each the flat C-order grid packed as
    np.packbits packs it (640 KB for the 400 x 400 x 32 grid): its observed voxels (FREE or OCCUPIED) and
    its FREE ones (OCCUPIED is observed and not free). points_ego (N, 3) returns, origins_ego (N, 3) or (3,)
    ray origins, metres in the ego frame."""
    points = _as_points(points_ego, "lidar_observation points_ego")
    origins = np.ascontiguousarray(np.broadcast_to(np.asarray(origins_ego, dtype=np.float64), points.shape))
    n_bytes = (int(np.prod(grid.shape)) + 7) // 8
    crossed, returned = np.zeros(n_bytes, np.uint8), np.zeros(n_bytes, np.uint8)
    mark_traversed(origins, np.ascontiguousarray(points), *grid_args(grid), crossed)
    returns = point_voxels(points, grid)
    mark_bits(returns[returns >= 0], returned)
    return crossed | returned, crossed & ~returned


def lidar_observation(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """uint8 (X, Y, Z): UNKNOWN 0, FREE 1 (a ray passed through before its return), OCCUPIED 2 (holds a
    return; wins over free). points_ego (N, 3) returns, origins_ego (N, 3) or (3,) ray origins, metres
    in the ego frame."""
    n = int(np.prod(grid.shape))
    observed, free = (np.unpackbits(bits, count=n) for bits in lidar_observation_bits(points_ego, origins_ego, grid))
    return (observed * np.uint8(OCCUPIED) - free).reshape(grid.shape)


def lidar_visibility(points_ego: np.ndarray, origins_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z) mask_lidar: voxels observed (free or occupied) by the rays origin -> return point
    (points (N, 3), origins (N, 3) or (3,), metres in the ego frame)."""
    return lidar_observation(points_ego, origins_ego, grid) != UNKNOWN


def _pixel_lattice(camera: CameraCalibration, angular_step_rad: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Pixel centres u (across), v (down) of a lattice over the camera's image with about `angular_step_rad`
    between neighbours, and its cell sizes (pixels): cell i of u covers [i * step_u, (i + 1) * step_u)."""
    K = np.asarray(camera.K, dtype=np.float64)
    step_u = max(1.0, K[0, 0] * angular_step_rad)
    step_v = max(1.0, K[1, 1] * angular_step_rad)
    return np.arange(step_u / 2.0, camera.width, step_u), np.arange(step_v / 2.0, camera.height, step_v), step_u, step_v


def camera_rays(camera: CameraCalibration, angular_step_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (R, 3) in the ego frame of rays through a pixel lattice of the
    camera's image with about `angular_step_rad` between neighbours (pinhole, OpenCV axes); ray
    i * len(v) + j goes through pixel (u[i], v[j]) of `_pixel_lattice`."""
    K = np.asarray(camera.K, dtype=np.float64)
    T = np.asarray(camera.T_ego_from_camera, dtype=np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4) or K[0, 0] <= 0 or K[1, 1] <= 0 or camera.width <= 0 or camera.height <= 0:
        raise VisibilityError(f"camera {camera.channel}: invalid intrinsics/extrinsics/size")
    u, v, _, _ = _pixel_lattice(camera, angular_step_rad)
    U, V = np.meshgrid(u, v, indexing="ij")
    x = (U.ravel() - K[0, 2] - K[0, 1] * (V.ravel() - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (V.ravel() - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=1)
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    return T[:3, 3].copy(), d_cam @ T[:3, :3].T


def _parent_cells(child: tuple, parent: tuple) -> np.ndarray:
    """(len(u) * len(v), 9) int64: per ray of the child lattice (`_pixel_lattice` of one camera), the
    parent lattice's rays of the cell holding its pixel (the last cell for a pixel past the last whole cell)
    and of the 8 cells around it (clipped at the image border), as ray indices of the parent lattice."""
    u, v, _, _ = child
    pu, pv, step_u, step_v = parent
    iu = np.minimum((u / step_u).astype(np.int64), len(pu) - 1)
    iv = np.minimum((v / step_v).astype(np.int64), len(pv) - 1)
    around = np.arange(-1, 2)
    cu = np.clip(iu[:, None] + around, 0, len(pu) - 1)  # (len(u), 3)
    cv = np.clip(iv[:, None] + around, 0, len(pv) - 1)  # (len(v), 3)
    cells = cu[:, None, :, None] * len(pv) + cv[None, :, None, :]  # (len(u), len(v), 3, 3)
    return cells.reshape(len(u) * len(v), 9)


@dataclass(frozen=True)
class RayBand:
    """The camera rays of one range band (ego frame, m): starts (R, 3) their cameras' origins, ends (R, 3)
    at the band's far end along the ray (far_m from its camera); resume_t: the band's near end as a fraction of a segment; t_block:
    the fraction before which occupied voxels do not occlude (near_m / far end); parents: (R, 9) int64, the
    previous band's rays of the parent cell and its 8 neighbours (None for the nearest band)."""

    starts: np.ndarray
    ends: np.ndarray
    far_m: float
    resume_t: float
    t_block: float
    parents: np.ndarray | None


@dataclass(frozen=True)
class CameraSegments:
    """The camera rays of a rig by range band, nearest first (see module doc)."""

    bands: list[RayBand]


def camera_segments(cameras: list[CameraCalibration], grid: GridSpec = DEFAULT_GRID, max_range_m: float = 60.0,
                    angular_step_rad: float | None = None, near_m: float = 0.5, range_bands: int = 3) -> CameraSegments:
    """The rays of all cameras in `range_bands` range bands (see module doc); angular_step_rad: the step of
    the farthest band's lattice (voxel_size / max_range_m by default), doubled per nearer band."""
    if range_bands < 1:
        raise VisibilityError(f"camera_segments: range_bands must be >= 1, got {range_bands}")
    far_step = grid.voxel_size / max_range_m if angular_step_rad is None else angular_step_rad
    bands, previous = [], None
    for k in reversed(range(range_bands)):
        far, near = max_range_m / 2**k, (max_range_m / 2 ** (k + 1) if k < range_bands - 1 else 0.0)
        starts, ends, parents, placed = [np.zeros((0, 3))], [np.zeros((0, 3))], [np.zeros((0, 9), np.int64)], []
        first = 0  # this camera's first ray in the band
        for c, camera in enumerate(cameras):
            origin, dirs = camera_rays(camera, far_step * 2**k)
            lattice = _pixel_lattice(camera, far_step * 2**k)
            starts.append(np.broadcast_to(origin, dirs.shape))
            ends.append(origin + dirs * far)
            if previous is not None:
                parent_lattice, parent_first = previous[c]
                parents.append(_parent_cells(lattice, parent_lattice) + parent_first)
            placed.append((lattice, first))
            first += len(dirs)
        bands.append(RayBand(np.concatenate(starts), np.concatenate(ends), far, near / far, near_m / far,
                             np.concatenate(parents) if previous is not None else None))
        previous = placed
    return CameraSegments(bands)


@numba.njit(cache=True)
def _walk_starts(parents: np.ndarray, reached: np.ndarray, unblocked_m: np.ndarray, far_m: float, resume_t: float,
                 margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Per ray of a band (parents (R, 9): its previous band's rays, see `RayBand`): where its walk starts, as a
    fraction of its segment (resume_t when all 9 reached their far end, inf when none did, else margin_m
    before the least of their unblocked_m), and that least unblocked distance as a fraction (the stop of a
    ray not walked). reached (P,), unblocked_m (P,) m: the previous band's rays' outcomes."""
    from_t, stop_t = np.empty(len(parents)), np.empty(len(parents))
    for r in range(len(parents)):
        every, some, least = True, False, np.inf
        for k in range(parents.shape[1]):
            p = parents[r, k]
            every = every and reached[p]
            some = some or reached[p]
            least = min(least, unblocked_m[p])
        stop_t[r] = least / far_m
        from_t[r] = resume_t if every else (max((least - margin_m) / far_m, 0.0) if some else np.inf)
    return from_t, stop_t


def visible_along(occupied: np.ndarray, segments: CameraSegments, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """bool (X, Y, Z): the voxels the camera rays `segments` see (module doc), each ray's up to and including
    its first occupied one. occupied: bool (X, Y, Z) in the ego frame."""
    if tuple(occupied.shape) != tuple(grid.shape):
        raise VisibilityError(f"camera_visibility: occupied has shape {occupied.shape}, grid {grid.shape}")
    occ = np.asarray(occupied, dtype=bool).ravel()
    visible = np.zeros(occ.shape, dtype=bool)
    reached, unblocked_m = np.zeros(0, dtype=bool), np.zeros(0)
    for band in segments.bands:
        if band.parents is None:
            from_t, stop_t = np.zeros(len(band.ends)), np.zeros(len(band.ends))
        else:
            from_t, stop_t = _walk_starts(band.parents, reached, unblocked_m, band.far_m, band.resume_t,
                                          RESUME_MARGIN_VOXELS * grid.voxel_size)
        reached = np.empty(len(band.ends), dtype=bool)
        mark_visible_to_first_hit(band.starts, band.ends, *grid_args(grid), occ, band.t_block, from_t, visible, reached,
                                  stop_t)
        unblocked_m = stop_t * band.far_m
    return visible.reshape(grid.shape)


def camera_visibility(occupied: np.ndarray, cameras: list[CameraCalibration], grid: GridSpec = DEFAULT_GRID,
                      max_range_m: float = 60.0, angular_step_rad: float | None = None,
                      near_m: float = 0.5, range_bands: int = 3) -> np.ndarray:
    """bool (X, Y, Z) mask_camera: voxels some camera sees (see module doc). occupied: bool (X, Y, Z)
    occupancy in the ego frame; cameras: calibrations with T_ego_from_camera."""
    return visible_along(occupied, camera_segments(cameras, grid, max_range_m, angular_step_rad, near_m, range_bands),
                         grid)
