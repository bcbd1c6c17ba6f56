"""Ground-layer labeling: a tree over a road stays OTHER; the paper's column stamp gets it wrong."""

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import OTHER, OTHER_GROUND, ROAD, ROAD_LINE
from benchmarks.paper_method import paper_column_stamp
from nuplan_occ.voxel.ground import (
    estimate_ground_height, ground_height_index, label_background, lowest_occupied_height,
)

GRID = GridSpec(x_min=-8, x_max=8, y_min=-8, y_max=8, z_min=-3, z_max=5, voxel_size=0.25)
GROUND_K = 6  # z in [-1.5, -1.25)


def scene():
    occ = np.zeros(GRID.shape, dtype=bool)
    occ[:, :, GROUND_K] = True
    occ[30:34, 30:34, :] = False  # a patch with no ground seen under the canopy
    occ[28:36, 28:36, 20:24] = True  # tree canopy 2 m above the road
    occ[10, 10, 7:14] = True  # a pole
    bev = np.full(GRID.shape[:2], ROAD, dtype=np.uint8)
    bev[:, :8] = OTHER_GROUND
    bev[:, 40] = ROAD_LINE
    return occ, bev


def test_ground_height_ignores_canopy_and_fills_gaps():
    occ, _ = scene()
    h = estimate_ground_height(occ, GRID)
    expected = GRID.z_min + (GROUND_K + 0.5) * 0.25
    assert np.allclose(h, expected)
    assert np.all(ground_height_index(h, GRID) == GROUND_K)
    assert np.all(np.isnan(estimate_ground_height(np.zeros(GRID.shape, bool), GRID)))


def test_tree_over_road_stays_other_and_road_below_is_road():
    occ, bev = scene()
    sem = label_background(occ, bev, GRID)
    assert np.all(sem[28:36, 28:36, 20:24] == OTHER)
    assert sem[28, 28, GROUND_K] == ROAD and sem[5, 5, GROUND_K] == OTHER_GROUND and sem[20, 40, GROUND_K] == ROAD_LINE
    assert np.all(sem[10, 10, 9:14] == OTHER)  # the pole above the ground layer
    assert np.all(sem[~occ] == 0)
    # the paper's column stamp turns the canopy and the pole into road
    paper = paper_column_stamp(np.where(occ, OTHER, 0).astype(np.uint8), bev == ROAD, bev == ROAD_LINE, GRID)
    assert np.all(paper[28:36, 28:36, 20:24] == ROAD) and np.all(paper[10, 10, 9:14] == ROAD)


def test_sloped_ground_with_curb_kept_at_voxel_precision():
    occ = np.zeros(GRID.shape, dtype=bool)
    i = np.arange(GRID.shape[0])
    k = 4 + i // 8  # a ramp, one layer up every 2 m
    occ[i, :, k] = True
    occ[:, 50:, :] = False
    occ[i, 50:, k + 1] = True  # a one-voxel curb along y
    h = estimate_ground_height(occ, GRID)
    assert np.array_equal(ground_height_index(h, GRID), k[:, None] + (np.arange(64)[None, :] >= 50))


def test_label_background_equals_the_columnwise_formula():
    rng = np.random.default_rng(2)
    occ = rng.random(GRID.shape) < 0.3
    bev = rng.choice([ROAD, OTHER_GROUND, ROAD_LINE], size=GRID.shape[:2]).astype(np.uint8)
    z = GRID.z_min + (np.arange(GRID.shape[2]) + 0.5) * GRID.voxel_size
    h = rng.choice(z, size=GRID.shape[:2]) + rng.choice([0.0, 0.3, -0.3, 0.31, 0.1], size=GRID.shape[:2])
    h[rng.random(GRID.shape[:2]) < 0.1] = np.nan  # unknown ground: OTHER
    with np.errstate(invalid="ignore"):
        near = np.abs(z[None, None, :] - h[:, :, None]) <= 0.3 + 1e-9
    expected = np.where(occ, np.where(near, bev[:, :, None], OTHER), 0)
    assert np.array_equal(label_background(occ, bev, GRID, 0.3, h), expected)


def test_lowest_occupied_height_is_the_centre_of_each_columns_lowest_voxel():
    occ, _ = scene()
    h = lowest_occupied_height(occ, GRID)
    assert h[0, 0] == GRID.z_min + (GROUND_K + 0.5) * 0.25
    assert h[30, 30] == GRID.z_min + (20 + 0.5) * 0.25  # canopy over the patch without ground
    assert h[34, 34] == h[0, 0]  # canopy over ground: the ground
    occ[5, 5, :] = False
    occ[5, 5, GRID.shape[2] - 1] = True  # only the top layer
    h = lowest_occupied_height(occ, GRID)
    assert h[5, 5] == GRID.z_min + (GRID.shape[2] - 0.5) * 0.25
    occ[6, 6, :] = False
    assert np.isnan(lowest_occupied_height(occ, GRID)[6, 6])
