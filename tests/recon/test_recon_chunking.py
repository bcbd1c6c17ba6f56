"""Chunk tiles of a reconstruction: point selection against brute force, dense cores halved to a point budget,
and chunk-by-chunk normals against normals estimated over the whole input. Points are metres in a local scene
frame."""

from __future__ import annotations

import numpy as np
from conftest import box_scan, plane_scan

from nuplan_occ.recon.chunking import ChunkTiles, budgeted_cores, chunk_normals
from nuplan_occ.recon.normals import estimate_normals
from nuplan_occ.recon.params import ReconParams


def _street(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    ground, ground_origins = plane_scan(rng, size=12.0, n=40000)
    box, box_origins = box_scan(rng, np.array([1.0, 0.75, 0.5]))
    shift = np.array([2.0, -1.5, 0.5])
    return np.concatenate([ground, box + shift]), np.concatenate([ground_origins, box_origins + shift])


def test_tiles_select_the_points_of_a_grown_core():
    points, _ = _street(np.random.default_rng(0))
    params = ReconParams(chunk_size=3.0)
    tiles = ChunkTiles.of(points, params)
    assert len(tiles.cores()) == 16
    u = (points[:, :2] - tiles.anchor[:2]) / params.voxel_size
    owned = np.concatenate([tiles.near(lo, hi, 0.0) for lo, hi in tiles.cores()])
    np.testing.assert_array_equal(np.sort(owned), np.arange(len(points)))  # every point in exactly one core
    for reach in (0.0, 3.0, 20.0):
        for lo, hi in tiles.cores()[::5]:
            brute = np.flatnonzero(np.all((u >= lo - reach) & (u < hi + reach), axis=1))
            np.testing.assert_array_equal(tiles.near(lo, hi, reach), brute)


def test_dense_cores_are_halved_to_the_point_budget():
    points, _ = _street(np.random.default_rng(2))
    params = ReconParams(chunk_size=12.0, chunk_overlap=0.5)  # one 12 m core
    tiles = ChunkTiles.of(points, params)
    assert len(tiles.cores()) == 1
    reach = params.chunk_overlap / params.voxel_size
    budget = len(points) // 5
    parts = list(budgeted_cores(tiles, reach, budget))
    assert len(parts) >= 5
    for lo, hi, near in parts:
        np.testing.assert_array_equal(near, tiles.near(lo, hi, reach))
        assert len(near) <= budget or (hi - lo).max() // 2 <= 2 * reach  # over budget only where halving stops
    assert sum(len(near) > budget for _, _, near in parts) <= 2  # the dense box's parts
    owned = np.concatenate([tiles.near(lo, hi, 0.0) for lo, hi, _ in parts])
    np.testing.assert_array_equal(np.sort(owned), np.arange(len(points)))  # the parts still tile the core
    unbudgeted = list(budgeted_cores(tiles, reach, 0))
    assert len(unbudgeted) == 1 and len(unbudgeted[0][2]) == len(points)
    narrow = list(budgeted_cores(tiles, 20.0, budget))  # halves no wider than twice the overlap: kept whole
    assert len(narrow) == 1


def test_chunk_normals_match_whole_input_normals():
    points, origins = _street(np.random.default_rng(1))
    params = ReconParams(chunk_size=3.0)
    tiles = ChunkTiles.of(points, params)
    whole = estimate_normals(points, origins, params.normal_knn)
    reach = params.chunk_overlap / params.voxel_size
    for lo, hi in tiles.cores():
        near = tiles.near(lo, hi, reach)
        chunked = chunk_normals(tiles, near, lo, hi, reach, lambda index: origins[index], params.normal_knn)
        assert chunked.dtype == np.float32 and chunked.shape == (len(near), 3)
        cosine = np.einsum("ij,ij->i", chunked, whole[near])
        assert np.mean(cosine > np.cos(np.radians(1.0))) > 0.999  # same neighbours, same sensor-facing sign
        assert np.all(np.einsum("ij,ij->i", chunked, origins[near] - points[near]) >= 0)
