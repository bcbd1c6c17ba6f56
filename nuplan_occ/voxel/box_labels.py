"""Per-frame check that no box with LiDAR points of its own is lost from the written grid.

A box "has points" when at least one of its track's own points of that frame (the points inside its
corrected box) lies inside the grid; it is "labeled" when the grid holds at least one voxel of its
class and its instance id. The manifest's `qa_boxes_with_points` / `qa_boxes_labeled` count them.
Everything is in the frame's ego frame (metres); pure numpy.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import yaw_matrix
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import Boxes
from nuplan_occ.labels import LABELS


def boxes_with_points(boxes: Boxes, track_points: dict[str, tuple[np.ndarray, np.ndarray]],
                      grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(K,) bool per box of `boxes` (ego frame): one of its track's points, given in that box's frame
    (track -> (points (n, 3), sensor origins) as the track stage's `object_points`), is inside the grid."""
    out = np.zeros(len(boxes), dtype=bool)
    for k, track in enumerate(boxes.track_tokens):
        points = track_points.get(track, (np.zeros((0, 3)), None))[0]
        if len(points):
            ego = np.asarray(points, np.float64) @ yaw_matrix(float(boxes.yaws[k])).T + boxes.centers[k]
            out[k] = bool(grid.point_to_index(ego)[1].any())
    return out


def boxes_labeled(boxes: Boxes, instance_ids: dict[str, int], semantics: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """(K,) bool per box: the grid (semantics uint8, instance uint16, same shape) has a voxel of the box's
    class (its category's label id) and its track's instance id (`instance_ids`; 0 for unknown tracks,
    which is background and never counts)."""
    occupied = instance > 0
    present = np.unique(instance[occupied].astype(np.int64) * 256 + semantics[occupied])
    keys = np.array([instance_ids.get(t, 0) * 256 + LABELS.box_category_to_id[c]
                     for t, c in zip(boxes.track_tokens, boxes.categories)], dtype=np.int64)
    labeled = np.isin(keys, present)
    labeled[[instance_ids.get(t, 0) == 0 for t in boxes.track_tokens]] = False
    return labeled


def box_label_columns(boxes: Boxes, track_points: dict[str, tuple[np.ndarray, np.ndarray]],
                      instance_ids: dict[str, int], semantics: np.ndarray, instance: np.ndarray,
                      grid: GridSpec = DEFAULT_GRID) -> dict[str, int]:
    """qa_boxes_with_points (boxes with >= 1 own point in the grid) and qa_boxes_labeled (of those, the
    ones with >= 1 voxel of their class and instance) of one frame."""
    has_points = boxes_with_points(boxes, track_points, grid)
    labeled = has_points & boxes_labeled(boxes, instance_ids, semantics, instance)
    return {"qa_boxes_with_points": int(has_points.sum()), "qa_boxes_labeled": int(labeled.sum())}
