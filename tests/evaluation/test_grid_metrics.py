"""Metrics on hand-made grids."""

import numpy as np
import pytest

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import OTHER, ROAD, VEHICLE
from nuplan_occ.evaluation.grid_metrics import (MetricsError, ground_hole_rate, occupancy_metrics, trail_count,
                                      unannotated_objects)


def test_occupancy_metrics():
    truth = np.zeros((4, 4, 2), np.uint8)
    pred = np.zeros_like(truth)
    truth[0, :, 0] = ROAD  # 4 road voxels
    truth[1, 0, 1] = VEHICLE
    pred[0, :3, 0] = ROAD  # 3 of 4 road
    pred[0, 3, 0] = OTHER  # wrong class, still occupied
    pred[2, 2, 1] = VEHICLE  # vehicle in the wrong place
    m = occupancy_metrics(pred, truth)
    assert m["iou"] == pytest.approx(4 / 6)
    assert m["per_class"][ROAD] == pytest.approx(3 / 4) and m["per_class"][VEHICLE] == 0.0
    assert m["per_class"][OTHER] == 0.0 and m["miou"] == pytest.approx((0.75 + 0.0) / 2)
    mask = np.zeros(truth.shape, bool)
    mask[0] = True
    masked = occupancy_metrics(pred, truth, mask, class_ids=[ROAD])
    assert masked["iou"] == 1.0 and masked["per_class"] == {ROAD: 0.75} and masked["n_voxels"] == 8
    with pytest.raises(MetricsError):
        occupancy_metrics(pred, truth[:2])


def test_trail_count_and_ground_holes():
    sem = np.zeros((3, 3, 4), np.uint8)
    swept = np.zeros(sem.shape, bool)
    swept[:, 1, 1:3] = True  # 6 voxels a car swept through
    now = np.zeros(sem.shape, bool)
    now[2, 1, 1:3] = True  # 2 of them occupied by the car now
    sem[0, 1, 1] = sem[2, 1, 1] = VEHICLE  # one ghost, one real
    assert trail_count(sem, swept, now) == 1
    sem[:, :, 0] = ROAD
    sem[0, 0, 0] = 0
    sem[1, 1, 0] = 0
    sem[1, 1, 1] = OTHER  # occupied one layer up: within tolerance
    drivable = np.ones((3, 3), bool)
    drivable[2, 2] = False
    k = np.zeros((3, 3), int)
    k[0, 2] = -1  # unknown ground: not counted
    assert ground_hole_rate(sem, drivable, k) == pytest.approx(1 / 7)
    assert ground_hole_rate(sem, drivable, k, tolerance_voxels=0) == pytest.approx(2 / 7)


def test_unannotated_objects_are_the_instances_no_box_holds():
    """Two objects on the default grid: a 2 x 1 m car at x = 10 m with a box yawed 90 degrees (its length
    along y), and one at x = -10 m that the log does not annotate. Only the second one's voxels are flagged;
    a box 2 m off the first object's centroid (beyond the 1 m growth) flags both."""
    grid = DEFAULT_GRID
    instance = np.zeros(grid.shape, np.uint16)
    first = grid.point_to_index(np.array([[10.1, -0.9, 0.1], [10.9, 0.9, 0.9]]))[0]
    second = grid.point_to_index(np.array([[-10.9, -0.4, 0.1], [-9.1, 0.4, 0.9]]))[0]
    for (lo, hi), track in (((first[0], first[1]), 7), ((second[0], second[1]), 9)):
        instance[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1] = track
    size = np.array([[2.0, 1.0, 1.0]])
    flagged = unannotated_objects(instance, np.array([[10.5, 0.0, 0.5]]), np.array([np.pi / 2]), size, grid)
    assert np.array_equal(flagged, instance == 9)
    missed = unannotated_objects(instance, np.array([[10.5, 3.2, 0.5]]), np.array([np.pi / 2]), size, grid)
    assert np.array_equal(missed, instance > 0)
    assert not unannotated_objects(np.zeros(grid.shape, np.uint16), np.zeros((0, 3)), np.zeros(0),
                                   np.zeros((0, 3)), grid).any()
