"""The report's top-down picture and flag rules against grids and columns with known answers."""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import make_transform, yaw_matrix
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import LABELS
from nuplan_occ.report.flags import evaluate_rules
from nuplan_occ.report.topdown import EMPTY_RGB, PATH_RGB, draw_path, path_pixels, render_topdown


def test_topdown_shows_the_top_voxel_forward_up_and_left_left():
    semantics = np.zeros(DEFAULT_GRID.shape, dtype=np.uint8)
    front, left = DEFAULT_GRID.point_to_index(np.array([[40.0, 0.0, 0.0], [0.0, 40.0, 0.0]]))[0]
    semantics[front[0], front[1], 2] = 12          # road low in the column ...
    semantics[front[0], front[1], 20] = 2          # ... under a vehicle: the vehicle is seen from above
    semantics[left[0], left[1], 3] = 4
    image = render_topdown(semantics, LABELS.palette())
    rows, cols = 400 - 1 - front[0], 400 - 1 - front[1]
    assert rows < 50 and 195 <= cols <= 205       # 40 m ahead: near the top edge, centred
    assert np.argmax(image[rows, cols]) == 0 and image[rows, cols, 0] > 150  # vehicle orange, bright (high)
    r, c = 400 - 1 - left[0], 400 - 1 - left[1]
    assert 195 <= r <= 205 and c < 50             # 40 m to the left: near the left edge
    assert (image[r, c] == (LABELS.palette()[4] * (0.55 + 0.45 * 3 / 31)).astype(np.uint8)).all()
    assert (image[0, 0] == EMPTY_RGB).all()


def test_ego_path_runs_from_behind_to_the_picture_centre():
    pose = make_transform(yaw_matrix(0.3), np.array([100.0, 50.0, 0.0]))
    behind = [make_transform(yaw_matrix(0.3), pose[:3, :3] @ np.array([-d, 0.0, 0.0]) + pose[:3, 3]) for d in (20, 10, 0)]
    pixels = path_pixels(np.stack(behind), pose, DEFAULT_GRID)
    assert pixels[:, 0].min() >= 199 and pixels[:, 0].max() == 200 + 80 - 1  # 20 m behind: 80 px below centre
    assert np.abs(pixels[:, 1] - 199).max() <= 1
    image = draw_path(np.zeros((400, 400, 3), np.uint8), pixels)
    assert (image[260, 199] == PATH_RGB).all() and (image[200, 200] == 255).all()


def test_rules_flag_known_frames_and_skip_absent_columns():
    ok = np.array([True, True, True, False])
    columns = {"status": np.array(["ok"] * 3 + ["failed"], dtype=object),
               "qa_pose_correction_m": np.array([0.1, 0.7, 0.2, np.nan]),
               "qa_lidar_observed_fraction": np.array([0.3, 0.32, 0.1, np.nan])}
    result = evaluate_rules(columns, ok)
    assert result.masks["failed"].tolist() == [False, False, False, True]
    assert result.masks["pose"].tolist() == [False, True, False, False]
    assert result.masks["low_observed"].tolist() == [False, False, True, False]  # median 0.3: 0.1 < 0.15
    assert "qa_boxes_with_points" in result.skipped["unlabeled_boxes"]
    assert result.flagged.tolist() == [False, True, True, True]
