"""Per-frame QA of boxes with points of their own: inside the grid, and labeled with class and instance."""

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.io.types import Boxes
from nuplan_occ.labels import BARRIER, TRAFFIC_CONE, VEHICLE
from nuplan_occ.voxel.box_labels import box_label_columns, boxes_labeled, boxes_with_points

GRID = GridSpec(x_min=-4, x_max=4, y_min=-4, y_max=4, z_min=-2, z_max=2, voxel_size=0.25)


def boxes() -> Boxes:
    """cone (in the grid), bollard (in the grid), car (centre outside, a corner inside), far cone, untracked."""
    centers = np.array([[1.0, 1.0, 0.0], [-2.0, 0.0, 0.0], [5.5, 0.0, 0.0], [20.0, 0.0, 0.0], [0.0, -2.0, 0.0]])
    sizes = np.array([[0.4, 0.4, 0.7], [0.2, 0.2, 0.9], [4.0, 2.0, 1.5], [0.4, 0.4, 0.7], [0.4, 0.4, 0.7]])
    return Boxes("ego", centers, sizes, np.array([0.0, 0.3, np.pi, 0.0, 0.0]), np.zeros((5, 3)),
                 ["traffic_cone", "barrier", "vehicle", "traffic_cone", "traffic_cone"],
                 ["cone", "bollard", "car", "far", "ghost"], ["a", "b", "c", "d", "e"])


def test_boxes_with_points_count_own_points_inside_the_grid():
    pts = {"cone": (np.zeros((3, 3)), None), "bollard": (np.zeros((0, 3)), None),
           "car": (np.array([[1.8, 0.0, 0.0]]), None),  # car frame, yaw pi: ego x = 5.5 - 1.8 = 3.7, in the grid
           "far": (np.zeros((2, 3)), None), "ghost": (np.zeros((1, 3)), None)}
    assert boxes_with_points(boxes(), pts, GRID).tolist() == [True, False, True, False, True]


def test_a_box_is_labeled_by_a_voxel_of_its_class_and_instance():
    ids = {"cone": 1, "bollard": 2, "car": 3, "far": 4}
    sem = np.zeros(GRID.shape, np.uint8)
    inst = np.zeros(GRID.shape, np.uint16)
    sem[20, 20, 8], inst[20, 20, 8] = TRAFFIC_CONE, 1       # the cone
    sem[5, 16, 8], inst[5, 16, 8] = VEHICLE, 2              # instance of the bollard but the wrong class
    sem[30, 16, 8], inst[30, 16, 8] = VEHICLE, 3            # the car
    assert boxes_labeled(boxes(), ids, sem, inst).tolist() == [True, False, True, False, False]
    pts = {t: (np.zeros((1, 3)), None) for t in ("cone", "bollard", "ghost")}
    assert box_label_columns(boxes(), pts, ids, sem, inst, GRID) == {"qa_boxes_with_points": 3, "qa_boxes_labeled": 1}
    sem[5, 16, 8] = BARRIER
    assert box_label_columns(boxes(), pts, ids, sem, inst, GRID) == {"qa_boxes_with_points": 3, "qa_boxes_labeled": 2}
