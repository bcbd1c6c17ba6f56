"""nuplan_occ.stages.filter: short scenes are filtered sweep by sweep; long ones (aggregate_min_sweeps) pass their sweeps
through and leave the same test to the aggregate; method "none" passes every sweep through."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from nuplan_occ.stages.filter import FilterParams, run


class _Scene:
    sensor_origin_ego = np.array([0.0, 0.0, 1.8])

    def background_positions(self, stride: int, min_sweeps: int) -> list[int]:
        return [0, 1]

    def ok_indices(self) -> list[int]:
        return [0, 1]


def _sweep_background(rng: np.random.Generator) -> np.ndarray:
    wall = np.c_[np.full(4000, 10.0), rng.uniform(-5, 5, 4000), rng.uniform(0, 3, 4000)]
    return np.vstack([wall, [[3.0, 20.0, 6.0]]])  # one isolated return far from the wall


def test_none_keeps_every_point_and_range_drops_the_isolated_one():
    rng = np.random.default_rng(0)
    clouds = [_sweep_background(rng), _sweep_background(rng)]
    inputs = {"scene": _Scene(), "splits": [SimpleNamespace(background=SimpleNamespace(xyz=c)) for c in clouds]}
    passed = run(inputs, replace(FilterParams(), method="none", aggregate_min_sweeps=2))
    assert all(np.array_equal(out, c) for out, c in zip(passed["background"], clouds))
    assert passed["outliers_removed"] == [0, 0] and passed["aggregate_outliers"] is None
    filtered = run(inputs, replace(FilterParams(), aggregate_min_sweeps=3))  # 2 loaded sweeps: a short scene
    kept = list(filtered["background"])
    assert all(not np.any(np.all(k == [3.0, 20.0, 6.0], axis=1)) for k in kept)
    assert all(r >= 1 for r in filtered["outliers_removed"]) and filtered["aggregate_outliers"] is None


def test_a_long_scene_leaves_its_test_to_the_aggregate():
    rng = np.random.default_rng(0)
    clouds = [_sweep_background(rng), _sweep_background(rng)]
    inputs = {"scene": _Scene(), "splits": [SimpleNamespace(background=SimpleNamespace(xyz=c)) for c in clouds]}
    params = replace(FilterParams(), aggregate_min_sweeps=2)
    deferred = run(inputs, params)
    assert all(np.array_equal(out, c) for out, c in zip(deferred["background"], clouds))
    assert deferred["outliers_removed"] == [0, 0]
    assert deferred["aggregate_outliers"] == {"method": params.method, "nb_neighbors": params.nb_neighbors,
                                              "std_ratio": params.std_ratio, "k_sigma": params.k_sigma}


class _CountingSplits(list):
    """The splits as a stored sequence: records which positions were read."""

    def __init__(self, items) -> None:
        super().__init__(items)
        self.read: list[int] = []

    def __getitem__(self, k):
        self.read.append(k)
        return super().__getitem__(k)

    def __iter__(self):
        return (self[k] for k in range(len(self)))


def test_only_the_background_positions_splits_are_read():
    rng = np.random.default_rng(0)
    clouds = [_sweep_background(rng) for _ in range(3)]  # _Scene takes positions 0 and 1 only
    splits = _CountingSplits(SimpleNamespace(background=SimpleNamespace(xyz=c)) for c in clouds)
    out = list(run({"scene": _Scene(), "splits": splits}, replace(FilterParams(), aggregate_min_sweeps=2))["background"])
    assert splits.read == [0, 1]
    assert np.array_equal(out[0], clouds[0]) and np.array_equal(out[1], clouds[1]) and out[2] is None
