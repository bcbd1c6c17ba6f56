"""nuplan_occ.aggregation.split.cleared_background: background points beyond max_range_m of their sweep's ego are
dropped."""

import numpy as np

from nuplan_occ.aggregation.split import cleared_background


def test_points_beyond_the_range_are_dropped_and_the_rest_kept():
    cloud = np.array([[10.0, 0.0, 0.5], [0.0, -74.9, 0.0], [60.0, 60.0, 1.0], [-90.0, 5.0, 1.2], [0.0, 0.0, 80.0]])
    kept = cleared_background(cloud, None, max_range_m=75.0, clearance_m=-1.0, ground_keep_m=0.03)
    # x-y distance decides: 84.9 m and 90.1 m are dropped, a point high above the ego stays
    assert np.array_equal(kept, cloud[[0, 1, 4]])


def test_no_limit_keeps_every_point():
    cloud = np.array([[500.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    assert np.array_equal(cleared_background(cloud, None, max_range_m=0.0, clearance_m=-1.0, ground_keep_m=0.03), cloud)
