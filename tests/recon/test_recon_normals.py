"""Point normals (`nuplan_occ.recon.normals`): per point and per cell, against the exact normals of analytic
shapes, and their orientation toward each point's own sensor origin."""

from __future__ import annotations

import numpy as np
from conftest import box_scan, sphere_scan

from nuplan_occ.recon.normals import estimate_normals


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def test_sphere_normals_point_outward_per_point_and_per_cell():
    pts, origins = sphere_scan(np.random.default_rng(3), n=30000, noise=0.005)
    exact = pts / np.linalg.norm(pts, axis=1, keepdims=True)  # the sensors are outside: normals face out
    per_point = estimate_normals(pts, origins, knn=30)
    per_cell = estimate_normals(pts, origins, knn=30, cell_m=0.125)
    for normals in (per_point, per_cell):
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
        assert np.median(_angle_deg(normals, exact)) < 3.0 and np.percentile(_angle_deg(normals, exact), 99) < 12.0
    assert len(np.unique(per_cell, axis=0)) < len(pts) / 3  # shared within cells, up to the per-point sign


def test_cell_normals_take_each_points_own_side():
    """Both faces of a 4 cm thin box share cells of 0.125 m: one PCA per cell, but every point's normal faces
    the sensor that saw it (the opposite sides of the slab get opposite normals)."""
    pts, origins = box_scan(np.random.default_rng(4), np.array([2.0, 2.0, 0.02]), noise=0.002)
    faces = np.abs(pts[:, 2]) > 0.015  # the top and bottom faces
    inner = faces & (np.abs(pts[:, :2]).max(axis=1) < 1.8)  # away from the edges
    for cell_m in (0.0, 0.125):
        normals = estimate_normals(pts, origins, knn=30, cell_m=cell_m)
        assert np.all(np.sign(normals[inner, 2]) == np.sign(pts[inner, 2]))
        assert np.median(np.abs(normals[inner, 2])) > 0.95  # neighbours reach across the slab's 4 cm


def test_the_normals_of_some_points_are_those_of_the_whole_estimate():
    """`which` asks for a subset (here the half of a sphere with x < 0.2, whose cells straddle the cut): every
    point still serves as a neighbour and a cell's centroid is that of all its points, so the rows equal the
    whole estimate's."""
    pts, origins = sphere_scan(np.random.default_rng(5), n=20000, noise=0.005)
    which = np.flatnonzero(pts[:, 0] < 0.2)
    for cell_m in (0.0, 0.125):
        whole = estimate_normals(pts, origins, knn=30, cell_m=cell_m)
        np.testing.assert_array_equal(estimate_normals(pts, origins[which], knn=30, cell_m=cell_m, which=which),
                                      whole[which])
