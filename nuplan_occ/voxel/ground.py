"""Local ground height of each grid column and ground-layer labeling of background voxels (numpy/scipy; the
labeling loop is a numba kernel).

Heights are metres in the EGO frame (z up), per column (i, j) of the grid.

Ground estimate (a one-window progressive morphological filter, as used for LiDAR ground filtering):
1. h0 = centre height of the lowest occupied voxel of each column (unknown where the column is empty);
2. empty columns take the h0 of the nearest known column if it lies within `fill_radius_m`
   (else they stay NaN at the end);
3. a 3x3 grey closing removes single-column pits (noise below the ground);
4. a grey opening over `window_m` x `window_m` removes raised blobs narrower than the window
   (vehicles, canopy, posts whose column has no ground) while keeping slopes and wide steps exactly;
5. a column keeps its own h0 where it is within `bump_tolerance_m` of the opened surface (curbs and
   small steps survive at voxel precision), else takes the opened height.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import OTHER


class GroundError(ValueError):
    """Grid arrays whose shapes do not match the grid spec."""


def _check_shape(array: np.ndarray, shape: tuple[int, ...], name: str) -> None:
    if tuple(array.shape) != tuple(shape):
        raise GroundError(f"{name}: expected shape {tuple(shape)}, got {tuple(array.shape)}")


def lowest_occupied_height(occupied: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(X, Y) float64: centre z (m, ego frame) of the lowest occupied voxel per column, NaN if none."""
    _check_shape(occupied, grid.shape, "lowest_occupied_height")
    heights = np.full(grid.shape[:2], np.nan)
    _lowest_occupied(np.asarray(occupied, dtype=bool), float(grid.z_min), float(grid.voxel_size), heights)
    return heights


@numba.njit(cache=True)
def _lowest_occupied(occupied: np.ndarray, z_min: float, voxel_size: float, heights: np.ndarray) -> None:
    """heights[i, j] = z_min + (k + 0.5) * voxel_size for the lowest occupied k of column (i, j); columns
    without one keep their value."""
    for i in range(occupied.shape[0]):
        for j in range(occupied.shape[1]):
            for k in range(occupied.shape[2]):
                if occupied[i, j, k]:
                    heights[i, j] = z_min + (k + 0.5) * voxel_size
                    break


def estimate_ground_height(occupied: np.ndarray, grid: GridSpec = DEFAULT_GRID, window_m: float = 4.0,
                           fill_radius_m: float = 3.0, bump_tolerance_m: float = 0.5) -> np.ndarray:
    """(X, Y) float64 ground height per column, metres in the ego frame; NaN where unknown.

    occupied: bool (X, Y, Z) background occupancy (objects excluded). See the module doc for the method.
    """
    h0 = lowest_occupied_height(occupied, grid)
    known = np.isfinite(h0)
    if not known.any():
        return h0
    dist, (ni, nj) = ndimage.distance_transform_edt(~known, return_indices=True)
    filled = h0[ni, nj]
    reachable = dist * grid.voxel_size <= fill_radius_m
    closed = ndimage.grey_closing(filled, size=(3, 3), mode="nearest")
    width = max(1, int(round(window_m / grid.voxel_size)) | 1)
    opened = ndimage.grey_opening(closed, size=(width, width), mode="nearest")
    ground = np.where(known & (filled - opened <= bump_tolerance_m), filled, opened)
    return np.where(reachable, ground, np.nan)


def label_background(background_occupied: np.ndarray, bev: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                     ground_tolerance_m: float = 0.3, ground_height: np.ndarray | None = None) -> np.ndarray:
    """uint8 (X, Y, Z) semantics of background voxels: 0 where not occupied; occupied voxels whose centre
    is within ground_tolerance_m of the column's ground height take the column's BEV class; all others
    (above the ground layer, or in columns of unknown ground) are OTHER (1). A tree over a road column
    therefore stays OTHER while the road surface under it becomes ROAD.

    bev: uint8 (X, Y) column classes (see bev.rasterize_bev); ground_height: optional precomputed
    (X, Y) heights (m, ego frame); estimated from background_occupied when None.
    """
    _check_shape(background_occupied, grid.shape, "label_background background_occupied")
    _check_shape(bev, grid.shape[:2], "label_background bev")
    if ground_height is None:
        ground_height = estimate_ground_height(background_occupied, grid)
    _check_shape(ground_height, grid.shape[:2], "label_background ground_height")
    z = grid.z_min + (np.arange(grid.shape[2]) + 0.5) * grid.voxel_size
    out = np.zeros(grid.shape, dtype=np.uint8)
    _label_ground_layer(np.asarray(background_occupied, dtype=bool), np.asarray(bev, dtype=np.uint8),
                        np.asarray(ground_height, dtype=np.float64), z, ground_tolerance_m + 1e-9, out)
    return out


@numba.njit(cache=True)
def _label_ground_layer(occupied: np.ndarray, bev: np.ndarray, ground_height: np.ndarray, z: np.ndarray,
                        tolerance: float, out: np.ndarray) -> None:
    """out[i, j, k] = bev[i, j] where occupied and |z[k] - ground_height[i, j]| <= tolerance, OTHER where
    occupied otherwise (also where the height is NaN); out starts zero."""
    for i in range(occupied.shape[0]):
        for j in range(occupied.shape[1]):
            h = ground_height[i, j]
            for k in range(occupied.shape[2]):
                if occupied[i, j, k]:
                    out[i, j, k] = bev[i, j] if abs(z[k] - h) <= tolerance else OTHER


def ground_height_index(ground_height: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(X, Y) int64 voxel layer index of the ground height; -1 where unknown or outside the z range."""
    with np.errstate(invalid="ignore"):
        k = np.floor((ground_height - grid.z_min) / grid.voxel_size)
        valid = np.isfinite(k) & (k >= 0) & (k < grid.shape[2])
    return np.where(valid, np.nan_to_num(k, nan=-1), -1).astype(np.int64)
