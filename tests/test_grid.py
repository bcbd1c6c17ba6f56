"""Grid helpers on exact inputs."""

import numpy as np

from nuplan_occ.grid import column_runs


def test_column_runs_lists_each_run_bottom_up_and_skips_empty_runs():
    column, layer = column_runs(np.array([3, 7, 0]), np.array([2, 0, 3]))
    assert column.tolist() == [0, 0, 2, 2, 2]
    assert layer.tolist() == [3, 4, 0, 1, 2]
    column, layer = column_runs(np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert len(column) == 0 and len(layer) == 0
