"""nuplan_occ.aggregation.dynamic.movers_by_frame: a sweep's points in the downsampling cells whose kept aggregate
point was removed as dynamic, moved into the scene frame."""

import numpy as np

from nuplan_occ.aggregation.dynamic import movers_by_frame


def test_points_in_flagged_cells_are_returned_in_the_scene_frame():
    aggregate = np.array([[10.02, 0.02, 0.02], [20.02, 0.02, 0.02]])  # kept points of cells [10, 10.05) and [20, 20.05)
    dynamic = np.array([True, False])
    shift = np.eye(4)
    shift[:3, 3] = [10.0, 0.0, 0.0]  # sweep 3's ego sits at scene x = 10
    cloud = np.array([[0.04, 0.01, 0.01],   # scene (10.04, ..): the flagged cell, though not its kept point
                      [10.01, 0.01, 0.01],  # scene (20.01, ..): a cell kept as static
                      [0.06, 0.01, 0.01]])  # scene (10.06, ..): the next cell, not flagged
    movers = movers_by_frame(aggregate, dynamic, [(3, cloud), (5, cloud[:0])], {3: shift, 5: np.eye(4)}, 0.05)
    assert set(movers) == {3, 5} and movers[5].shape == (0, 3)
    assert movers[3].dtype == np.float32
    np.testing.assert_allclose(movers[3], [[10.04, 0.01, 0.01]], atol=1e-6)
