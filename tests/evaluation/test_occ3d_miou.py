"""occ3d_miou on a known confusion matrix: free counted in the matrix but not in the mean, absent classes NaN."""

import numpy as np
import pytest

from nuplan_occ.evaluation.datasets import confusion
from nuplan_occ.evaluation.occ3d_miou import occ3d_miou
from nuplan_occ.labels import BARRIER, EMPTY, OTHER_GROUND, PEDESTRIAN, ROAD, VEHICLE

IDS = [EMPTY, VEHICLE, PEDESTRIAN, ROAD, OTHER_GROUND]
KNOWN = np.array([  # rows: truth id, columns: predicted id, in the order of IDS
    [50, 3, 0, 2, 4],
    [5, 20, 1, 0, 0],
    [2, 0, 6, 0, 0],
    [1, 0, 0, 30, 0],
    [0, 0, 0, 0, 0],  # other_ground: only ever predicted (4 voxels), never true
])


def _grids_of(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pred, truth) uint8 grids of shape (n, 1, 1) whose confusion over IDS is `matrix`."""
    pairs = [(t, p) for i, t in enumerate(IDS) for j, p in enumerate(IDS) for _ in range(matrix[i, j])]
    truth, pred = np.array(pairs, dtype=np.uint8).T
    order = np.random.default_rng(3).permutation(len(pairs))
    return pred[order].reshape(-1, 1, 1), truth[order].reshape(-1, 1, 1)


def test_known_confusion_matrix_gives_the_hand_computed_figures():
    pred, truth = _grids_of(KNOWN)
    # voxels outside the mask: would change every figure if they were counted
    pred = np.concatenate([pred, np.full((40, 1, 1), VEHICLE, np.uint8)])
    truth = np.concatenate([truth, np.full((40, 1, 1), ROAD, np.uint8)])
    mask = np.zeros(truth.shape, dtype=bool)
    mask[: KNOWN.sum()] = True
    conf = confusion(pred, truth, mask)
    assert conf[np.ix_(IDS, IDS)].tolist() == KNOWN.tolist() and conf.sum() == KNOWN.sum()

    result = occ3d_miou(conf, [VEHICLE, PEDESTRIAN, ROAD, OTHER_GROUND, BARRIER])
    # vehicle: 20 / (row 26 + column 23 - 20); pedestrian 6 / (8 + 7 - 6); road 30 / (31 + 32 - 30)
    expected = {VEHICLE: 20 / 29, PEDESTRIAN: 6 / 9, ROAD: 30 / 33, OTHER_GROUND: 0.0}
    for class_id, iou in expected.items():
        assert result["per_class"][class_id] == pytest.approx(iou)
    assert np.isnan(result["per_class"][BARRIER])  # in neither grid: NaN, left out of the mean
    assert result["miou"] == pytest.approx(np.mean(list(expected.values())))
    assert result["free_iou"] == pytest.approx(50 / (59 + 58 - 50))  # free: in the matrix, not in the mean
    # occupied in both: 124 - 59 - 58 + 50 = 57; occupied in either: 124 - 50
    assert result["geometry_iou"] == pytest.approx(57 / 74)
    assert result["n_voxels"] == 124


def test_free_predicted_for_an_object_counts_against_that_class():
    truth = np.array([VEHICLE] * 4 + [EMPTY] * 4, np.uint8).reshape(-1, 1, 1)
    pred = np.array([VEHICLE] * 2 + [EMPTY] * 6, np.uint8).reshape(-1, 1, 1)
    result = occ3d_miou(confusion(pred, truth), [VEHICLE, ROAD])
    assert result["per_class"][VEHICLE] == 0.5 and result["miou"] == 0.5 and np.isnan(result["per_class"][ROAD])
    assert result["free_iou"] == pytest.approx(4 / 6)
