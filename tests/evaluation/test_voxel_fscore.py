"""voxel_fscore: a slab predicted 2 voxels further along x, hand-counted at three thresholds."""

import numpy as np
import pytest

from nuplan_occ.evaluation.voxel_fscore import voxel_fscore
from nuplan_occ.labels import ROAD, VEHICLE
from tools_world import SMALL


def _slab(x0: int) -> np.ndarray:
    sem = np.zeros(SMALL.shape, np.uint8)
    sem[x0:x0 + 4, 8:20, 2:5] = VEHICLE
    return sem


@pytest.mark.parametrize("threshold, expected", [(0.6, 1.0), (0.3, 0.75), (0.2, 0.5)])
def test_slab_shifted_two_voxels(threshold, expected):
    """Truth x indices 10-13, prediction 12-15 (0.25 m voxels): predicted layers 12, 13 lie on the truth,
    14 is 0.25 m from it and 15 0.5 m; truth layers 13, 12 likewise, 11 at 0.25 m and 10 at 0.5 m. So
    precision = recall = share of the 4 layers within the threshold."""
    result = voxel_fscore(_slab(12), _slab(10), SMALL, threshold_m=threshold)
    assert result["precision"] == pytest.approx(expected) and result["recall"] == pytest.approx(expected)
    assert result["fscore"] == pytest.approx(expected)


def test_mask_labels_and_empty_grids():
    truth = _slab(10)
    pred = np.where(truth > 0, ROAD, 0).astype(np.uint8)  # labels do not matter, only occupancy
    pred[25:, 25:, 7] = VEHICLE  # 49 voxels far from the slab, outside the mask
    mask = np.ones(SMALL.shape, dtype=bool)
    mask[25:, 25:, 7] = False
    masked = voxel_fscore(pred, truth, SMALL, mask)
    assert masked["precision"] == 1.0 and masked["recall"] == 1.0 and masked["fscore"] == 1.0
    unmasked = voxel_fscore(pred, truth, SMALL)
    assert unmasked["precision"] == pytest.approx(144 / 193) and unmasked["recall"] == 1.0
    empty = np.zeros_like(truth)
    assert voxel_fscore(empty, truth, SMALL)["fscore"] == 0.0
    assert voxel_fscore(truth, empty, SMALL)["fscore"] == 0.0
    assert np.isnan(voxel_fscore(empty, empty, SMALL)["fscore"])
