"""`reconstruct` with every method, input validation, Surface sampling and the metrics."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import curb_scan

from nuplan_occ.grid import GridSpec
from nuplan_occ.recon import ReconError, ReconParams, Surface, reconstruct, surface_metrics, voxel_iou
from benchmarks.recon_bench import compare_methods


def test_all_methods_run_through_reconstruct_and_score():
    rng = np.random.default_rng(10)
    pts, origins = curb_scan(rng, n=20000)
    truth, _ = curb_scan(rng, n=60000, noise=0.0)
    rows = compare_methods(pts, origins, truth, params=ReconParams(poisson_depth=8))
    by_method = {row["method"]: row for row in rows}
    assert set(by_method) == {"nksr", "poisson", "none"}
    for row in rows:
        assert row["time_s"] >= 0 and row["points_per_s"] > 0
        assert row["fscore@0.25"] > 0.9, row
    assert by_method["nksr"]["faces"] > 0 and by_method["poisson"]["faces"] > 0
    assert by_method["nksr"]["precision@0.25"] > 0.95
    raw = reconstruct(pts, origins, method="none", frame="box")
    assert raw.faces.shape == (0, 3) and raw.frame == "box"
    assert np.array_equal(raw.sample_points(0.1), pts.astype(np.float32).astype(np.float64))  # Surface precision


@pytest.mark.parametrize(
    "points, origins, method",
    [
        (np.zeros((100, 2)), np.zeros((100, 2)), "nksr"),
        (np.zeros((100, 3)), np.zeros((99, 3)), "nksr"),
        (np.full((100, 3), np.nan), np.zeros((100, 3)), "poisson"),
        (np.zeros((10, 3)), np.zeros((10, 3)), "nksr"),
        (np.zeros((100, 3)), np.zeros((100, 3)), "marching"),
    ],
)
def test_bad_input_raises(points, origins, method):
    with pytest.raises(ReconError):
        reconstruct(points, origins, method=method)


def test_origins_given_per_sweep_give_the_surface_of_per_point_origins():
    rng = np.random.default_rng(11)
    pts, origins = curb_scan(rng, n=20000)
    sweeps = np.unique(origins, axis=0, return_inverse=True)
    per_point = reconstruct(pts, origins)
    per_sweep = reconstruct(pts, sweeps[0], origin_ids=sweeps[1].ravel())
    assert len(sweeps[0]) < 10 and len(per_point.faces) > 0
    np.testing.assert_array_equal(per_sweep.vertices, per_point.vertices)
    np.testing.assert_array_equal(per_sweep.faces, per_point.faces)
    for table, ids in ((sweeps[0], sweeps[1].ravel()[:-1]), (sweeps[0], sweeps[1].ravel() + len(sweeps[0]))):
        with pytest.raises(ReconError, match="origin_ids"):
            reconstruct(pts, table, origin_ids=ids)


def test_bad_params_raise():
    with pytest.raises(ReconError, match="voxel_size"):
        ReconParams(voxel_size=0.0)
    with pytest.raises(ReconError, match="degree"):
        ReconParams(degree=3)


def test_sample_points_cover_triangles_at_the_spacing():
    vertices = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.0, 1.0, 1.0], [5.0, 5.0, 5.0]])
    surface = Surface(vertices=vertices, faces=np.array([[0, 1, 2]]), frame="scene")
    samples = surface.sample_points(0.1)
    assert np.allclose(samples[:, 2], 1.0)
    assert np.all(samples[:, 0] >= -1e-12) and np.all(samples[:, 0] / 2 + samples[:, 1] <= 1 + 1e-12)
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 1, (2, 2000))
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    probe = np.column_stack([2 * a, b, np.ones_like(a)])
    gaps = np.linalg.norm(probe[:, None] - samples[None], axis=2).min(axis=1)
    assert gaps.max() <= 0.1
    with pytest.raises(ValueError):
        Surface(vertices=vertices, faces=np.array([[0, 1, 4]]), frame="scene")


def test_surface_metrics_known_values():
    rng = np.random.default_rng(1)
    truth = np.column_stack([rng.uniform(0, 10, (5000, 2)), np.zeros(5000)])
    same = surface_metrics(truth, truth)
    assert same["chamfer"] == 0 and same["fscore@0.1"] == 1 and same["fscore@0.25"] == 1
    shifted = surface_metrics(truth + [0, 0, 0.2], truth)
    assert np.isclose(shifted["chamfer"], 0.2)
    assert shifted["precision@0.1"] == 0 and shifted["recall@0.25"] == 1
    empty = surface_metrics(np.zeros((0, 3)), truth)
    assert empty["chamfer"] == np.inf and empty["fscore@0.25"] == 0


def test_voxel_iou_known_values():
    grid = GridSpec(x_min=0, x_max=2, y_min=0, y_max=2, z_min=0, z_max=1, voxel_size=0.5)
    a = np.array([[0.1, 0.1, 0.1], [1.1, 0.1, 0.1]])
    b = np.array([[0.2, 0.2, 0.2], [1.6, 1.6, 0.6], [9.0, 9.0, 9.0]])  # the last is outside the grid
    assert np.isclose(voxel_iou(a, b, grid), 1 / 3)
    observable = np.zeros(grid.shape, dtype=bool)
    observable[0, 0, 0] = True
    assert voxel_iou(a, b, grid, observable) == 1.0
