"""Fixtures of the occgen tests: a small synthetic dataset (64 x 64 x 8 cells)."""

from __future__ import annotations

import pytest

from nuplan_occ.grid import GridSpec
from benchmarks.occgen_bench import make_synthetic_dataset

SMALL_GRID = GridSpec(x_min=-8.0, x_max=8.0, y_min=-8.0, y_max=8.0, z_min=-1.0, z_max=1.0)


@pytest.fixture(scope="session")
def small_grid() -> GridSpec:
    return SMALL_GRID


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> str:
    """3 scenes x 8 frames of synthetic road / road_line / other_ground + vehicles, 64 x 64 x 8."""
    return make_synthetic_dataset(str(tmp_path_factory.mktemp("occgen") / "ds"), scenes=3, frames=8,
                                  grid=SMALL_GRID)
