"""stages.filter: method "none" passes every sweep's background through (the filter then runs on the aggregate)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from stages.filter import FilterParams, run


class _Scene:
    sensor_origin_ego = np.array([0.0, 0.0, 1.8])

    def background_positions(self, stride: int, min_sweeps: int) -> list[int]:
        return [0, 1]


def _sweep_background(rng: np.random.Generator) -> np.ndarray:
    wall = np.c_[np.full(4000, 10.0), rng.uniform(-5, 5, 4000), rng.uniform(0, 3, 4000)]
    return np.vstack([wall, [[3.0, 20.0, 6.0]]])  # one isolated return far from the wall


def test_none_keeps_every_point_and_range_drops_the_isolated_one():
    rng = np.random.default_rng(0)
    clouds = [_sweep_background(rng), _sweep_background(rng)]
    inputs = {"scene": _Scene(), "splits": [SimpleNamespace(background=SimpleNamespace(xyz=c)) for c in clouds]}
    passed = run(inputs, replace(FilterParams(), method="none"))
    assert all(np.array_equal(out, c) for out, c in zip(passed["background"], clouds))
    assert passed["outliers_removed"] == [0, 0]
    filtered = run(inputs, FilterParams())
    kept = list(filtered["background"])
    assert all(not np.any(np.all(k == [3.0, 20.0, 6.0], axis=1)) for k in kept)
    assert all(r >= 1 for r in filtered["outliers_removed"])
