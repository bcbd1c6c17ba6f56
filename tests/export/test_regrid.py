"""Consumers' grids and frames on hand-made grids with known answers (export.regrid)."""

import numpy as np
import pytest

from nuplan_occ.export.regrid import OCC3D_GRID, GridError, coarsen, coverage, target_grid, to_lidar_frame
from nuplan_occ.geometry import make_transform, rotation_from_euler
from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import LABELS

SRC = GridSpec(-2.0, 2.0, -2.0, 2.0, -1.0, 1.0, 0.25)  # 16 x 16 x 8
HALF = GridSpec(-2.0, 2.0, -2.0, 2.0, -1.0, 1.0, 0.5)  # 8 x 8 x 4
ROAD, LINE, CAR, PED = (LABELS.id_of(n) for n in ("road", "road_line", "vehicle", "pedestrian"))


def empty_frame(grid: GridSpec) -> dict:
    return {"semantics": np.zeros(grid.shape, np.uint8), "mask_lidar": np.zeros(grid.shape, bool),
            "mask_camera": np.zeros(grid.shape, bool), "instance": np.zeros(grid.shape, np.uint16),
            "flow": np.zeros((*grid.shape, 3), np.float16), "token": "t"}


def test_coarsen_to_half_metre_by_the_stated_rules():
    f = empty_frame(SRC)
    # block (0, 0, 0) = source [0:2, 0:2, 0:2]: 3 road, 1 road_line -> road (majority of the occupied)
    f["semantics"][0:2, 0:2, 0] = [[ROAD, ROAD], [ROAD, LINE]]
    # block (1, 0, 0): one car among 7 empty -> car (any occupied child); instance 5, flow (2, 0, 0)
    f["semantics"][2, 0, 0], f["instance"][2, 0, 0], f["flow"][2, 0, 0] = CAR, 5, (2.0, 0.0, 0.0)
    # block (2, 0, 0): 2 car (instances 7, 7) vs 2 pedestrian (instance 9, 0): tie -> pedestrian (precedence)
    f["semantics"][4, 0, 0:2] = CAR
    f["instance"][4, 0, 0:2] = 7
    f["semantics"][5, 0, 0:2] = PED
    f["instance"][5, 0, 0] = 9
    f["flow"][5, 0, 0:2] = [(1.0, 0.0, 0.0), (3.0, 0.0, 0.0)]  # mean of the pedestrian children: 2
    f["flow"][4, 0, 0:2] = (50.0, 0.0, 0.0)  # car children do not enter the mean
    # masks: one observed child is enough
    f["mask_lidar"][15, 15, 7] = True
    f["mask_camera"][0:2, 0:2, 0:2] = True
    out = coarsen(f, SRC, HALF)
    assert out["semantics"].shape == (8, 8, 4) and out["semantics"].dtype == np.uint8
    expected = np.zeros((8, 8, 4), np.uint8)
    expected[0, 0, 0], expected[1, 0, 0], expected[2, 0, 0] = ROAD, CAR, PED
    assert np.array_equal(out["semantics"], expected)
    assert out["instance"][1, 0, 0] == 5 and out["instance"][2, 0, 0] == 9 and out["instance"].sum() == 14
    assert np.allclose(out["flow"][1, 0, 0], (2, 0, 0)) and np.allclose(out["flow"][2, 0, 0], (2, 0, 0))
    assert np.count_nonzero(out["flow"]) == 2
    assert np.flatnonzero(out["mask_lidar"]).tolist() == [np.ravel_multi_index((7, 7, 3), (8, 8, 4))]
    assert np.flatnonzero(out["mask_camera"]).tolist() == [0]
    assert out["token"] == "t"


def test_coarsen_to_occ3d_children_and_uncovered_top():
    ours = GridSpec()
    assert target_grid("occ3d", ours) == OCC3D_GRID and OCC3D_GRID.shape == (200, 200, 16)
    covered = coverage(ours, OCC3D_GRID)
    # Occ3D's top layer [5.0, 5.4) m lies above our 5 m top: no children; every other voxel has some
    assert not covered[..., 15].any() and covered[..., :15].all()
    f = {"semantics": np.zeros(ours.shape, np.uint8), "mask_camera": np.ones(ours.shape, bool)}
    # our voxel centred at x = 0.125 (index 200) lies in Occ3D's x voxel [0, 0.4) (index 100); z centre
    # 0.125 m (index 12) in [-0.2, 0.2) (index 2)
    f["semantics"][200, 200, 12] = CAR
    # x centre 0.375 (index 201) is in the same Occ3D voxel; 0.625 (index 202) is in the next one
    f["semantics"][202, 200, 12] = PED
    out = coarsen(f, ours, OCC3D_GRID)
    assert out["semantics"][100, 100, 2] == CAR and out["semantics"][101, 100, 2] == PED
    assert np.count_nonzero(out["semantics"]) == 2
    assert out["mask_camera"][..., :15].all() and not out["mask_camera"][..., 15].any()


def test_target_grid_names():
    assert target_grid("0.5m", GridSpec()).shape == (200, 200, 16)
    assert target_grid("1m", GridSpec()).shape == (100, 100, 8)
    for bad in ("0.3m", "fine", "-1m"):
        with pytest.raises(GridError):
            target_grid(bad, GridSpec())


def test_lidar_frame_by_whole_voxels_is_an_exact_shift():
    f = empty_frame(SRC)
    f["semantics"][10, 4, 6] = CAR
    f["flow"][10, 4, 6] = (1.0, 2.0, 0.0)
    f["mask_lidar"][10, 4, 6] = True
    # LiDAR 0.5 m forward (2 voxels) and 0.25 m up (1 voxel) of the rear axle
    out = to_lidar_frame(f, SRC, make_transform(np.eye(3), [0.5, 0.0, 0.25]))
    assert np.flatnonzero(out["semantics"]).tolist() == [np.ravel_multi_index((8, 4, 5), SRC.shape)]
    assert out["semantics"][8, 4, 5] == CAR and out["mask_lidar"][8, 4, 5] and out["mask_lidar"].sum() == 1
    assert np.allclose(out["flow"][8, 4, 5], (1, 2, 0))


def test_lidar_frame_rotation_moves_points_and_flow():
    f = empty_frame(SRC)
    f["semantics"][12, 8, 4] = CAR  # centre (1.125, 0.125, 0.125) m in the ego frame
    f["flow"][12, 8, 4] = (1.0, 0.0, 0.0)
    T = make_transform(rotation_from_euler(0.0, 0.0, np.pi / 2), [0.0, 0.0, 0.0])  # LiDAR yawed 90 deg left
    out = to_lidar_frame(f, SRC, T)
    # in the LiDAR frame the point is at (0.125, -1.125, 0.125): voxel (8, 3, 4)
    assert np.flatnonzero(out["semantics"]).tolist() == [np.ravel_multi_index((8, 3, 4), SRC.shape)]
    assert np.allclose(out["flow"][8, 3, 4], (0.0, -1.0, 0.0), atol=1e-3)
