"""Outlier filters on synthetic sweeps and an aggregate with injected outliers: 1 % uniform in the bounding box
(farther than 0.5 m from any real point) and 0.5 % floating 2-6 m from the sensor."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from fbsa_world import SENSOR_EGO, make_sequence
from scipy.spatial import cKDTree

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.aggregate import aggregate_background
from nuplan_occ.evaluation.step_metrics import outlier_scores
from nuplan_occ.points.outliers import remove_statistical_outliers


def _inject(points: np.ndarray, origins: np.ndarray, rng: np.random.Generator):
    """points (N, 3) with per-point sensor origins (N, 3) -> (all points, their origins, is_outlier)."""
    tree = cKDTree(points)
    uniform = rng.uniform(points.min(axis=0), points.max(axis=0), (len(points) // 30, 3))
    uniform = uniform[tree.query(uniform)[0] > 0.5][: len(points) // 100]
    src = rng.integers(0, len(points), len(points) // 200)
    direction = rng.normal(size=(len(src), 3))
    near = origins[src] + direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(2, 6, (len(src), 1))
    far_enough = tree.query(near)[0] > 0.5
    all_points = np.vstack([points, uniform, near[far_enough]])
    all_origins = np.vstack([origins, origins[rng.integers(0, len(points), len(uniform))], origins[src][far_enough]])
    return all_points, all_origins, np.arange(len(all_points)) >= len(points)


@pytest.fixture(scope="module")
def seq():
    return make_sequence(6, seed=3)


def _scores(points, origins, truth):
    return {m: outlier_scores(remove_statistical_outliers(points, m, origin=origins), truth)
            for m in ("global", "knn", "range")}


def test_filters_on_single_sweeps(seq):
    rng = np.random.default_rng(7)
    per_method: dict[str, list] = {"global": [], "knn": [], "range": []}
    for cloud in seq.clouds[:3]:
        pts, org, bad = _inject(cloud, np.tile(SENSOR_EGO, (len(cloud), 1)), rng)
        for method, score in _scores(pts, org, bad).items():
            per_method[method].append((score.caught, score.lost))
    mean = {m: np.mean(v, axis=0) for m, v in per_method.items()}
    print("single sweep (caught, lost):", {m: np.round(v, 4).tolist() for m, v in mean.items()})
    assert mean["range"][0] >= 0.65 and mean["range"][1] <= 0.01
    assert mean["knn"][0] >= 0.4
    assert mean["global"][0] < mean["range"][0] and mean["global"][1] > mean["range"][1]
    assert mean["range"][1] < mean["knn"][1]
    default = inspect.signature(remove_statistical_outliers).parameters["method"].default
    assert default == "range"  # chosen by this measurement


def test_filters_on_an_aggregate(seq):
    agg = aggregate_background(seq.clouds, np.tile(SENSOR_EGO, (len(seq.clouds), 1)), seq.truth,
                               voxel_downsample_m=0.05)
    pts, org, bad = _inject(agg.points, agg.frame_origins[agg.frame_ids], np.random.default_rng(8))
    scores = _scores(pts, org, bad)
    print("aggregate (caught, lost):", {m: (round(s.caught, 4), round(s.lost, 4)) for m, s in scores.items()})
    assert scores["range"].caught >= 0.75 and scores["range"].lost <= 0.005
    assert scores["range"].caught > scores["global"].caught


def test_global_rule_and_input_checks():
    rng = np.random.default_rng(0)
    blob = rng.normal(0, 1, (2000, 3))
    far = np.array([[50.0, 0, 0], [0, -60.0, 0]])
    keep = remove_statistical_outliers(np.vstack([blob, far]), "global", k_sigma=3.0)
    assert not keep[-2:].any() and keep[:-2].mean() > 0.97
    assert remove_statistical_outliers(blob[:5], "knn").all()  # too few points to judge
    with pytest.raises(PointInputError):
        remove_statistical_outliers(blob, "median")
    with pytest.raises(PointInputError):
        remove_statistical_outliers(blob[:, :2])
    with pytest.raises(PointInputError):
        remove_statistical_outliers(blob, "range", origin=np.zeros((3, 3)))


def knn_distances(points: np.ndarray, k: int, chunk_rows: int = 1 << 18) -> np.ndarray:
    """(N, k) distances of every point, assembled from `knn_distance_chunks`."""
    from nuplan_occ.points.knn import knn_distance_chunks

    distances = np.empty((len(points), k))
    for rows, chunk in knn_distance_chunks(points, k, chunk_rows):
        distances[rows] = chunk
    return distances


def test_knn_distances_equal_kd_tree_queries():
    rng = np.random.default_rng(5)
    ring = rng.normal(size=(3000, 3)) * [20.0, 20.0, 0.5]
    duplicates = np.repeat(rng.uniform(-1, 1, (50, 3)), 4, axis=0)  # ties and zero distances
    line = np.c_[np.linspace(0, 10, 300), np.zeros(300), np.zeros(300)]  # a degenerate (flat) box
    pile = np.repeat([[3.0, -2.0, 0.1]], 100, axis=0)  # one unsplittable leaf of more points than LEAF_SIZE_CAP
    twins = np.repeat([[5.5, 1.0, 0.0], [np.nextafter(5.5, 6.0), 1.0, 0.0]], 40, axis=0)  # x one float apart: the
    # midpoint of the node holding only them rounds onto its low end
    points = np.vstack([ring, duplicates, line, pile, twins])
    for k in (1, 2, 20):
        np.testing.assert_array_equal(knn_distances(points, k), cKDTree(points).query(points, k=k)[0].reshape(len(points), k))
    np.testing.assert_array_equal(knn_distances(points[:7], 7), cKDTree(points[:7]).query(points[:7], k=7)[0])
    with pytest.raises(ValueError):
        knn_distances(points[:3], 4)


def test_knn_distance_chunks_cover_every_point_once_with_the_whole_clouds_distances():
    from nuplan_occ.points.knn import knn_distance_chunks

    rng = np.random.default_rng(6)
    points = np.vstack([rng.normal(size=(5000, 3)) * [30.0, 10.0, 1.0], np.repeat([[1.0, 1.0, 0.0]], 90, axis=0)])
    whole = knn_distances(points, 8)
    chunks = list(knn_distance_chunks(points, 8, chunk_rows=700))
    assert len(chunks) > 5 and all(len(rows) < 700 + 100 for rows, _ in chunks)
    rows = np.concatenate([r for r, _ in chunks])
    np.testing.assert_array_equal(np.sort(rows), np.arange(len(points)))
    np.testing.assert_array_equal(np.vstack([d for _, d in chunks]), whole[rows])


def test_range_filter_takes_per_sweep_origins_through_ids():
    rng = np.random.default_rng(9)
    sweeps = np.array([[0.0, 0.0, 2.0], [40.0, 0.0, 2.0], [80.0, 0.0, 2.0]])
    ids = rng.integers(0, 3, 6000)
    points = sweeps[ids] + rng.normal(size=(6000, 3)) * [15.0, 15.0, 0.3]
    points[:30] += [0.0, 0.0, 25.0]  # floaters
    by_id = remove_statistical_outliers(points, origin=sweeps, origin_ids=ids)
    np.testing.assert_array_equal(by_id, remove_statistical_outliers(points, origin=sweeps[ids]))
    assert not by_id[:30].any() and by_id[30:].mean() > 0.95
    with pytest.raises(PointInputError):
        remove_statistical_outliers(points, origin=sweeps, origin_ids=ids[:10])
