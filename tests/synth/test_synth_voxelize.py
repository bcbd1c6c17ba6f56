"""Exact voxel overlap of prisms, triangles and ray segments against independent brute-force checks."""

from __future__ import annotations

import numpy as np
import shapely
from shapely.geometry import Polygon, box

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.synth.voxelize import prism_voxel_hits, reduce_labels, segment_voxels, triangle_voxel_hits

SMALL = GridSpec(x_min=-3.0, x_max=3.0, y_min=-3.0, y_max=3.0, z_min=-1.0, z_max=1.0, voxel_size=0.25)


def _unflat(flat: np.ndarray, grid: GridSpec) -> set[tuple[int, int, int]]:
    return {tuple(int(v) for v in np.unravel_index(f, grid.shape)) for f in np.unique(flat)}


def _columns(grid: GridSpec) -> tuple[np.ndarray, np.ndarray, list]:
    ii, jj = np.meshgrid(np.arange(grid.shape[0]), np.arange(grid.shape[1]), indexing="ij")
    x0 = grid.x_min + ii.ravel() * grid.voxel_size
    y0 = grid.y_min + jj.ravel() * grid.voxel_size
    squares = [box(a, b, a + grid.voxel_size, b + grid.voxel_size) for a, b in zip(x0, y0)]
    return ii.ravel(), jj.ravel(), squares


def _rect(center, half, yaw) -> Polygon:
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-u[1], u[0]])
    c = np.asarray(center)
    return Polygon([c + su * half[0] * u + sv * half[1] * v for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def test_prism_hits_match_shapely_overlap():
    rng = np.random.default_rng(3)
    ii, jj, squares = _columns(SMALL)
    for _ in range(6):
        center = rng.uniform(-2, 2, 2)
        half = rng.uniform(0.1, 1.2, 2)
        yaw = rng.uniform(-np.pi, np.pi)
        z0, z1 = sorted(rng.uniform(-0.9, 0.9, 2))
        flat, owner = prism_voxel_hits(center[None], half[None], np.array([yaw]), np.array([z0]), np.array([z1]), SMALL)
        assert np.all(owner == 0)
        hit_cols = shapely.intersects(_rect(center, half, yaw), squares)
        k0 = int(np.floor((z0 - SMALL.z_min) / SMALL.voxel_size))
        k1 = int(np.floor((z1 - SMALL.z_min) / SMALL.voxel_size))
        expected = {(int(i), int(j), k) for i, j in zip(ii[hit_cols], jj[hit_cols]) for k in range(k0, k1 + 1)}
        assert _unflat(flat, SMALL) == expected


def test_horizontal_face_on_a_voxel_plane_takes_one_layer():
    # z = 0 is the plane between layers 11 and 12 of the default grid: half-open voxels put it in 12 only
    flat, _ = prism_voxel_hits(np.zeros((1, 2)), np.array([[10.0, 10.0]]), np.zeros(1), np.zeros(1), np.zeros(1), DEFAULT_GRID)
    layers = {k for _, _, k in _unflat(flat, DEFAULT_GRID)}
    assert layers == {12}
    # the closed square [-10, 10]^2 reaches into the voxels starting at x = 10 and y = 10: 81 x 81 columns
    assert len(flat) == 81 * 81


def _triangle_meets_box(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Independent check: clip the triangle polygon by the 6 closed half-spaces of the box."""
    poly = [p for p in tri]
    for axis in range(3):
        for bound, sign in ((lo[axis], 1.0), (hi[axis], -1.0)):
            out = []
            for a, b in zip(poly, poly[1:] + poly[:1]):
                da, db = sign * (a[axis] - bound), sign * (b[axis] - bound)
                if da >= 0:
                    out.append(a)
                if (da >= 0) != (db >= 0):
                    out.append(a + (b - a) * (da / (da - db)))
            poly = out
            if not poly:
                return False
    return True


def test_triangle_hits_match_polygon_clipping():
    rng = np.random.default_rng(5)
    tris = rng.uniform(-1.5, 1.5, (5, 3, 3)) * [1, 1, 0.5]
    flat, owner = triangle_voxel_hits(tris, SMALL)
    got = {(t, *v) for t, f in zip(owner, flat) for v in _unflat(np.array([f]), SMALL)}
    s = SMALL.voxel_size
    for t, tri in enumerate(tris):
        lo_idx = np.maximum(np.floor((tri.min(0) - SMALL.lower) / s).astype(int) - 1, 0)
        hi_idx = np.minimum(np.floor((tri.max(0) - SMALL.lower) / s).astype(int) + 1, np.array(SMALL.shape) - 1)
        for i in range(lo_idx[0], hi_idx[0] + 1):
            for j in range(lo_idx[1], hi_idx[1] + 1):
                for k in range(lo_idx[2], hi_idx[2] + 1):
                    lo = SMALL.lower + np.array([i, j, k]) * s
                    assert _triangle_meets_box(tri, lo, lo + s) == ((t, i, j, k) in got), (t, i, j, k)


def test_segment_traversal_is_exact():
    rng = np.random.default_rng(7)
    origins = rng.uniform(-2.5, 2.5, (40, 3)) * [1, 1, 0.3]
    ends = origins + rng.normal(0, 3, (40, 3))
    got = _unflat(segment_voxels(origins, ends, SMALL), SMALL)
    # every voxel reported is crossed by some segment (slab test), and dense samples are all reported
    s = SMALL.voxel_size
    for idx in got:
        lo = SMALL.lower + np.array(idx) * s
        hi = lo + s
        d = ends - origins
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - origins) / d, (hi - origins) / d
        tn = np.nanmax(np.minimum(t1, t2), axis=1)
        tf = np.nanmin(np.maximum(t1, t2), axis=1)
        assert np.any((tn <= tf + 1e-9) & (tf >= -1e-9) & (tn <= 1 + 1e-9)), idx
    ts = np.linspace(0, 1, 4001)
    samples = (origins[:, None] + ts[None, :, None] * (ends - origins)[:, None]).reshape(-1, 3)
    idx, inside = SMALL.point_to_index(samples)
    assert {tuple(int(v) for v in row) for row in idx[inside]} <= got


def test_reduce_labels_priority_and_instance():
    flat = np.array([5, 5, 5, 9])
    rank = np.array([1, 5, 5, 2])
    label = np.array([13, 2, 4, 12])
    inst = np.array([0, 3, 7, 0])
    sem, ins = reduce_labels(flat, rank, label, inst, SMALL)
    assert sem.reshape(-1)[5] == 4 and ins.reshape(-1)[5] == 7
    assert sem.reshape(-1)[9] == 12 and ins.reshape(-1)[9] == 0
    assert np.count_nonzero(sem) == 2
