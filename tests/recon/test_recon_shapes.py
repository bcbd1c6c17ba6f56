"""NKSR-lite on noisy analytic shapes: accuracy, sign convention, step preservation, masking,
chunking. Points and origins are in a local "scene" frame, metres."""

from __future__ import annotations

import numpy as np
import torch
from conftest import box_scan, curb_scan, plane_scan, sphere_scan
from scipy.spatial import cKDTree

from nuplan_occ.recon import ReconParams, reconstruct, surface_metrics
from nuplan_occ.recon.chunking import lattice_anchor
from nuplan_occ.recon.nksr_lite import fit_field
from nuplan_occ.recon.normals import estimate_normals


def test_plane_is_recovered_and_faces_point_to_the_sensor():
    rng = np.random.default_rng(0)
    pts, origins = plane_scan(rng)
    surface = reconstruct(pts, origins)
    assert surface.frame == "scene" and surface.is_mesh
    assert np.abs(surface.vertices[:, 2]).max() < 0.03
    truth = np.column_stack([rng.uniform(-3, 3, (20000, 2)), np.zeros(20000)])
    metrics = surface_metrics(surface.sample_points(0.05), truth)
    assert metrics["chamfer"] < 0.04 and metrics["fscore@0.1"] > 0.97
    tri = surface.vertices[surface.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.mean(normals[:, 2] > 0) > 0.99  # wound toward f > 0, the sensor side


def test_field_sign_is_positive_on_the_sensor_side():
    rng = np.random.default_rng(1)
    pts, origins = sphere_scan(rng, n=15000)
    params = ReconParams()
    normals = estimate_normals(pts, origins, params.normal_knn)
    assert np.mean(np.einsum("ij,ij->i", normals, pts) > 0) > 0.99  # outward, toward the sensors
    anchor = lattice_anchor(pts, params)
    field, stats = fit_field(pts, normals, anchor, params)
    assert stats.relative_residual <= params.pcg_tolerance
    probe = pts[:2000] / np.linalg.norm(pts[:2000], axis=1, keepdims=True)
    for offset, sign in ((0.2, 1.0), (-0.2, -1.0)):
        u = torch.from_numpy((pts[:2000] + offset * probe - anchor) / params.voxel_size)
        values = field.evaluate(u).numpy()
        assert np.mean(np.sign(values) == sign) > 0.99
        # near the data f is a signed distance in voxel units
        assert abs(np.median(values) * params.voxel_size - offset) < 0.05
    on_surface = field.evaluate(torch.from_numpy((pts[:2000] - anchor) / params.voxel_size)).numpy()
    assert np.median(np.abs(on_surface)) * params.voxel_size < 0.01


def test_sphere_and_box_are_closed_and_accurate():
    rng = np.random.default_rng(2)
    pts, origins = sphere_scan(rng)
    sphere = reconstruct(pts, origins)
    radius = np.linalg.norm(sphere.vertices, axis=1)
    assert np.abs(radius - 1.5).max() < 0.06
    assert np.all(np.abs(sphere.vertices).max(axis=0) > 1.45)  # covers every side

    half = np.array([1.0, 0.75, 0.5])
    pts, origins = box_scan(rng, half)
    box = reconstruct(pts, origins, frame="box")
    assert box.frame == "box"
    truth, _ = box_scan(rng, half, n_per_m2=4000, noise=0.0)
    metrics = surface_metrics(box.sample_points(0.03), truth)
    assert metrics["chamfer"] < 0.05  # sharp edges are rounded at 0.25 m voxels
    assert metrics["fscore@0.1"] > 0.85 and metrics["precision@0.25"] > 0.97 and metrics["recall@0.25"] > 0.99


def test_curb_step_is_preserved():
    rng = np.random.default_rng(3)
    pts, origins = curb_scan(rng)
    surface = reconstruct(pts, origins)
    v = surface.vertices
    inner = (np.abs(v[:, 0]) < 3.5) & (np.abs(v[:, 1]) < 3.5)  # away from the data's border
    road = v[inner & (v[:, 1] < -0.6)]
    walk = v[inner & (v[:, 1] > 0.6)]
    assert np.abs(road[:, 2]).max() < 0.03
    assert np.abs(walk[:, 2] - 0.15).max() < 0.03
    # the curb face: vertices between the two levels sit near y = 0
    middle = v[inner & (v[:, 2] > 0.05) & (v[:, 2] < 0.1)]
    assert len(middle) > 0 and np.abs(middle[:, 1]).max() < 0.2


def test_no_surface_far_from_the_points():
    rng = np.random.default_rng(4)
    a, oa = plane_scan(rng, size=3.0, n=8000)
    b, ob = plane_scan(rng, size=3.0, n=8000)
    b[:, 0] += 8.0
    ob[:, 0] += 8.0
    pts, origins = np.concatenate([a, b]), np.concatenate([oa, ob])
    params = ReconParams()
    surface = reconstruct(pts, origins, params=params)
    distance, _ = cKDTree(pts).query(surface.vertices)
    assert distance.max() <= params.mask_distance
    assert not np.any((surface.vertices[:, 0] > 2.2) & (surface.vertices[:, 0] < 5.8))  # the gap stays empty
    above = pts + [0.0, 0.0, 1.0]  # a second, unseen layer is not invented either
    assert cKDTree(surface.vertices).query(above)[0].min() > 0.8


def test_small_hole_is_filled():
    rng = np.random.default_rng(5)
    pts, origins = plane_scan(rng, size=6.0, n=20000)
    hole = np.linalg.norm(pts[:, :2] - [0.5, 0.5], axis=1) < 0.3
    surface = reconstruct(pts[~hole], origins[~hole])
    grid = np.stack(np.meshgrid(np.linspace(0.3, 0.7, 5), np.linspace(0.3, 0.7, 5)), -1).reshape(-1, 2)
    probe = np.column_stack([grid, np.zeros(len(grid))])
    assert cKDTree(surface.sample_points(0.05)).query(probe)[0].max() < 0.05


def test_chunked_agrees_with_unchunked():
    rng = np.random.default_rng(6)
    ground, og = plane_scan(rng, size=10.0, n=30000)
    box, ob = box_scan(rng, np.array([1.0, 0.75, 0.5]))
    box = box + [1.0, -0.5, 0.5]
    keep = box[:, 2] > 0.02  # the bottom face is hidden by the ground
    pts, origins = np.concatenate([ground, box[keep]]), np.concatenate([og, ob[keep] + [1.0, -0.5, 0.5]])
    whole = reconstruct(pts, origins, params=ReconParams(chunk_size=0.0))
    chunked = reconstruct(pts, origins, params=ReconParams(chunk_size=4.0, chunk_overlap=2.0))
    assert len(chunked.info["chunks"]) == 9 and len(whole.info["chunks"]) == 1
    metrics = surface_metrics(chunked.sample_points(0.05), whole.sample_points(0.05), thresholds=(0.02, 0.05))
    assert metrics["chamfer"] < 0.01
    assert metrics["fscore@0.05"] > 0.99


def test_point_budget_agrees_with_unchunked():
    rng = np.random.default_rng(7)
    pts, origins = plane_scan(rng, size=10.0, n=30000)
    whole = reconstruct(pts, origins, params=ReconParams(chunk_size=0.0, chunk_max_points=0))
    halved = reconstruct(pts, origins, params=ReconParams(chunk_size=0.0, chunk_overlap=2.0, chunk_max_points=12000))
    assert len(halved.info["chunks"]) == 4 and len(whole.info["chunks"]) == 1
    metrics = surface_metrics(halved.sample_points(0.05), whole.sample_points(0.05), thresholds=(0.02, 0.05))
    assert metrics["chamfer"] < 0.01
    assert metrics["fscore@0.05"] > 0.99


def test_coarse_first_solve_keeps_shapes_signs_and_hole_filling():
    params = ReconParams(coarse_first=True)
    rng = np.random.default_rng(8)
    pts, origins = sphere_scan(rng)
    sphere = reconstruct(pts, origins, params=params)
    assert np.abs(np.linalg.norm(sphere.vertices, axis=1) - 1.5).max() < 0.06
    normals = estimate_normals(pts, origins, params.normal_knn)
    anchor = lattice_anchor(pts, params)
    field, stats = fit_field(pts, normals, anchor, params)
    assert stats.relative_residual <= params.pcg_tolerance
    probe = pts[:2000] / np.linalg.norm(pts[:2000], axis=1, keepdims=True)
    for offset, sign in ((0.2, 1.0), (-0.2, -1.0)):
        values = field.evaluate(torch.from_numpy((pts[:2000] + offset * probe - anchor) / params.voxel_size)).numpy()
        assert np.mean(np.sign(values) == sign) > 0.99
        assert abs(np.median(values) * params.voxel_size - offset) < 0.05

    half = np.array([1.0, 0.75, 0.5])
    pts, origins = box_scan(rng, half)
    truth, _ = box_scan(rng, half, n_per_m2=4000, noise=0.0)
    metrics = surface_metrics(reconstruct(pts, origins, params=params).sample_points(0.03), truth)
    assert metrics["chamfer"] < 0.05 and metrics["precision@0.25"] > 0.97 and metrics["recall@0.25"] > 0.99

    pts, origins = plane_scan(rng, size=6.0, n=20000)
    hole = np.linalg.norm(pts[:, :2] - [0.5, 0.5], axis=1) < 0.3
    surface = reconstruct(pts[~hole], origins[~hole], params=params)
    grid = np.stack(np.meshgrid(np.linspace(0.3, 0.7, 5), np.linspace(0.3, 0.7, 5)), -1).reshape(-1, 2)
    assert cKDTree(surface.sample_points(0.05)).query(np.column_stack([grid, np.zeros(len(grid))]))[0].max() < 0.05


def test_with_triangles_appends_a_mesh_and_its_info():
    from nuplan_occ.recon.surface import Surface

    triangle = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    surface = Surface(triangle, [[0, 1, 2]], "scene", {"method": "nksr"})
    joined = surface.with_triangles(triangle + [0.0, 0.0, 1.0], np.array([[0, 2, 1]]), ground_fill_faces=1)
    assert joined.frame == "scene" and joined.info == {"method": "nksr", "ground_fill_faces": 1}
    np.testing.assert_array_equal(joined.faces, [[0, 1, 2], [3, 5, 4]])
    np.testing.assert_array_equal(joined.vertices[3:], triangle + [0.0, 0.0, 1.0])
