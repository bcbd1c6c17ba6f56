"""Unboxed movers: a frame's dynamic points become voxels labeled by their cluster's size."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import OTHER, VEHICLE
from nuplan_occ.voxel.movers import mover_voxels


def _surface_points(center, size, spacing=0.1) -> np.ndarray:
    """Points on the x-facing and top faces of a box (what one sweep sees of it), ego frame."""
    cx, cy, cz = center
    lx, ly, lz = size
    ys, zs = np.meshgrid(np.arange(cy - ly / 2, cy + ly / 2, spacing), np.arange(cz - lz / 2, cz + lz / 2, spacing))
    back = np.column_stack([np.full(ys.size, cx - lx / 2), ys.ravel(), zs.ravel()])
    xs, ys = np.meshgrid(np.arange(cx - lx / 2, cx + lx / 2, spacing), np.arange(cy - ly / 2, cy + ly / 2, spacing))
    top = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, cz + lz / 2 - 0.01)])
    return np.vstack([back, top])


def test_clusters_are_labeled_by_footprint_and_noise_is_skipped() -> None:
    truck = _surface_points((20.1, 5.1, 0.6), (8.0, 2.5, 3.0))
    pedestrian = _surface_points((10.1, -8.1, 0.0), (0.5, 0.5, 1.7))
    speck = np.array([[-30.1, 30.1, 1.1]])
    outside = np.array([[70.0, 0.0, 0.0]])
    result = mover_voxels(np.vstack([truck, pedestrian, speck, outside]), DEFAULT_GRID)
    centres = DEFAULT_GRID.lower + (result.indices + 0.5) * DEFAULT_GRID.voxel_size
    near_truck = np.abs(centres[:, 0] - 20.1) < 4.5
    near_pedestrian = np.abs(centres[:, 0] - 10.1) < 1.0
    assert near_truck.sum() and np.all(result.class_ids[near_truck] == VEHICLE)
    assert near_pedestrian.sum() and np.all(result.class_ids[near_pedestrian] == OTHER)
    assert np.all(near_truck | near_pedestrian)  # the lone speck and the point beyond the grid are not painted
    expected = np.unique(DEFAULT_GRID.point_to_index(np.vstack([truck, pedestrian]))[0], axis=0)
    assert len(np.unique(result.indices, axis=0)) == len(result.indices) == len(expected)


def test_fragments_a_voxel_apart_count_as_one_object() -> None:
    """A truck's roof whose middle stayed in the background: a 1 m piece one empty voxel from the rest is
    part of the vehicle, while on its own (gap_voxels 0) it is too small to be one."""
    roof = _surface_points((20.1, 5.1, 0.6), (8.0, 1.0, 3.0))
    roof = roof[roof[:, 2] > 2.0]
    piece = roof[:, 0] < 17.0
    gap = (roof[:, 0] >= 17.0) & (roof[:, 0] < 17.25)
    joined = mover_voxels(roof[~gap], DEFAULT_GRID)
    alone = mover_voxels(roof[~gap], DEFAULT_GRID, gap_voxels=0)
    piece_voxels = np.unique(DEFAULT_GRID.point_to_index(roof[piece])[0], axis=0)
    def classes_of(result):
        hit = (result.indices[:, None, :] == piece_voxels[None]).all(axis=2).any(axis=1)
        return set(result.class_ids[hit].tolist())
    assert classes_of(joined) == {VEHICLE}
    assert classes_of(alone) == {OTHER}


def test_no_points_no_voxels() -> None:
    result = mover_voxels(np.zeros((0, 3)), DEFAULT_GRID)
    assert result.indices.shape == (0, 3) and result.class_ids.shape == (0,)
