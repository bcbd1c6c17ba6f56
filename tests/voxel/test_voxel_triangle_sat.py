"""The triangle/voxel kernel against exact geometry: rational-arithmetic overlap tests, and the cells a large
flat triangle covers (shapely polygons)."""

from fractions import Fraction

import numpy as np
import shapely

from nuplan_occ.voxel import voxelize
from nuplan_occ.voxel.triangle_sat import EPS


def exact_overlap(tri: np.ndarray, voxel: tuple[int, int, int]) -> bool:
    """Closed triangle (3, 3) vs closed cube [v-EPS, v+1-EPS]^3 in exact rational arithmetic (the SAT's 13
    axes: a convex pair is disjoint iff one of them separates it)."""
    eps, h = Fraction(EPS), Fraction(1, 2)
    center = [Fraction(int(c)) + h - eps for c in voxel]
    u = [[Fraction(float(tri[n, a])) - center[a] for a in range(3)] for n in range(3)]
    edges = [[u[(n + 1) % 3][a] - u[n][a] for a in range(3)] for n in range(3)]
    e0, e1 = edges[0], [u[2][a] - u[0][a] for a in range(3)]
    normal = [e0[1] * e1[2] - e0[2] * e1[1], e0[2] * e1[0] - e0[0] * e1[2], e0[0] * e1[1] - e0[1] * e1[0]]
    unit = [[Fraction(int(a == b)) for b in range(3)] for a in range(3)]
    cross = [[e[1] * f[2] - e[2] * f[1], e[2] * f[0] - e[0] * f[2], e[0] * f[1] - e[1] * f[0]]
             for e in unit for f in edges]
    for axis in unit + [normal] + cross:
        p = [sum(axis[a] * u[n][a] for a in range(3)) for n in range(3)]
        r = h * sum(abs(c) for c in axis)
        if min(p) > r or max(p) < -r:
            return False
    return True


def test_kernel_equals_exact_rational_overlap():
    rng = np.random.default_rng(3)
    tri = rng.uniform(-1, 1, size=(30, 3, 3)) * rng.choice([0.3, 1.0, 2.0], size=(30, 1, 1)) + rng.uniform(0, 6, (30, 1, 3))
    got = {tuple(v) for v in voxelize.triangle_voxel_indices(tri)}
    expected = set()
    for t in tri:
        first, last = np.floor(t.min(axis=0) + EPS).astype(int), np.floor(t.max(axis=0) + EPS).astype(int)
        for v in np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(first, last)], indexing="ij"), -1).reshape(-1, 3):
            if exact_overlap(t, tuple(v)):
                expected.add(tuple(int(c) for c in v))
    assert got == expected


def test_large_flat_triangle_covers_exactly_the_cells_it_meets():
    corners = np.array([[0.37, 0.81], [29.6, 3.3], [11.2, 27.9]])  # voxel units, ~30 voxels per edge
    tri = np.concatenate([corners, np.full((3, 1), 2.5)], axis=1)[None]
    got = voxelize.triangle_voxel_indices(tri)
    assert set(got[:, 2]) == {2}
    polygon = shapely.Polygon(corners)
    i, j = np.meshgrid(np.arange(-1, 32), np.arange(-1, 32), indexing="ij")
    cells = shapely.box(i.ravel() - EPS, j.ravel() - EPS, i.ravel() + 1 - EPS, j.ravel() + 1 - EPS)
    meets = shapely.intersects(cells, polygon)
    expected = np.stack([i.ravel()[meets], j.ravel()[meets]], axis=1)
    assert np.array_equal(got[:, :2], expected)


def test_unclipped_range_voxelized_in_several_boxes_equals_one_box(monkeypatch):
    rng = np.random.default_rng(4)
    tri = rng.uniform(-1, 1, size=(400, 3, 3)) * 3.0 + rng.uniform(-10, 10, size=(400, 1, 3))
    whole = voxelize.triangle_voxel_indices(tri)
    monkeypatch.setattr(voxelize, "TILE_EDGE", 4)
    assert np.array_equal(voxelize.triangle_voxel_indices(tri), whole)
