"""RayIoU: the ray pattern, the origins, first hits against brute force, and known answers of a shifted wall."""

import numpy as np
import pytest

from nuplan_occ.evaluation.ray_iou import (
    MAX_ORIGINS, SENSOR_ORIGIN_EGO, cast_rays, ray_counts, ray_directions, ray_elevations, ray_iou, ray_origins)
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import BARRIER, OTHER, PEDESTRIAN, VEHICLE
from tools_world import SMALL, street_scene

WIDE = GridSpec(x_min=-8.0, x_max=8.0, y_min=-64.0, y_max=64.0, z_min=-2.0, z_max=2.0, voxel_size=0.25)
"""64 x 512 x 16 voxels: wide in y so that oblique rays still meet a wall across x."""
ORIGIN = np.array([[0.125, 0.125, 0.125]])  # a voxel centre: no ray runs along a lattice plane
AZIMUTHS_DEG = np.array([0.0, 50.0, 70.0, 80.0, 84.0])


def _horizontal(azimuths_deg) -> np.ndarray:
    a = np.radians(azimuths_deg)
    return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)


def test_ray_pattern_is_the_stated_one():
    elevations = np.degrees(ray_elevations())
    assert len(elevations) == 39
    assert elevations[0] == pytest.approx(-45.0) and elevations[1] == pytest.approx(-np.degrees(np.arctan(1 / 2)))
    assert elevations[9] == pytest.approx(-np.degrees(np.arctan(1 / 10)))
    steps = np.diff(elevations[9:])
    assert np.allclose(steps, np.degrees(np.arctan(10) - np.arctan(9)))
    assert elevations[-2] < np.degrees(0.21) <= elevations[-1]
    dirs = ray_directions()
    assert dirs.shape == (39 * 360, 3) and np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
    azimuths = np.degrees(np.arctan2(dirs[:360, 1], dirs[:360, 0])) % 360
    assert np.allclose(azimuths, np.arange(360.0))


def test_origins_own_first_inside_the_grid_and_at_most_eight():
    yaw90 = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    poses = np.tile(np.eye(4), (21, 1, 1))
    poses[:, :3, :3] = yaw90
    poses[:, 0, 3] = 10.0 * np.arange(21)  # 10 m apart along global x = the ego's -y
    origins = ray_origins(poses, 2, DEFAULT_GRID)
    # frame i sits at ego y = -10 (i - 2); |y| < 49 keeps i = 0 .. 6
    expected_y = [0.0] + [-10.0 * (i - 2) for i in (0, 1, 3, 4, 5, 6)]
    assert np.allclose(origins[:, 1], expected_y)
    assert np.allclose(origins[:, [0, 2]], SENSOR_ORIGIN_EGO[[0, 2]])

    dense = np.tile(np.eye(4), (100, 1, 1))
    dense[:, 0, 3] = np.arange(100.0)
    picked = ray_origins(dense, 50, DEFAULT_GRID)
    assert len(picked) == MAX_ORIGINS and np.allclose(picked[0], SENSOR_ORIGIN_EGO)
    # the others: evenly spaced among frames 0 .. 97 bar 50 (ego x = i - 50 + 1.5185 inside (-49, 49))
    others = np.array([0, 16, 32, 48, 65, 81, 97])
    assert np.allclose(picked[1:, 0], others - 50 + SENSOR_ORIGIN_EGO[0])

    dense[:10] = np.nan
    assert np.allclose(ray_origins(dense, 5, DEFAULT_GRID), SENSOR_ORIGIN_EGO[None])


def test_first_hits_match_dense_sampling_along_the_rays():
    rng = np.random.default_rng(11)
    sem = np.where(rng.random(SMALL.shape) < 0.03, rng.integers(1, 9, SMALL.shape), 0).astype(np.uint8)
    origins = rng.uniform(SMALL.lower + 0.5, SMALL.upper - 0.5, (4, 3))
    dirs = rng.normal(size=(100, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    labels, depths = cast_rays(sem, origins, dirs, SMALL)
    step = 1e-3
    s = np.arange(0.0, 20.0, step)
    agree = 0
    for r, (o, d) in enumerate((o, d) for o in origins for d in dirs):
        idx, inside = SMALL.point_to_index(o + s[:, None] * d)
        hit = inside & (sem[tuple(idx.T)] > 0)
        if not hit.any():
            agree += labels[r] == 0 and np.isinf(depths[r])
            continue
        k = np.argmax(hit)
        agree += labels[r] == sem[tuple(idx[k])] and abs(depths[r] - s[k]) <= step
    assert agree >= 398  # of 400: only a corner clipped by less than the 1 mm sampling step may differ


def test_prediction_shifted_two_voxels_along_x_gives_the_known_rayiou():
    """A vehicle wall across x at [4, 4.5) m, predicted at [4.5, 5) m (2 voxels further): horizontal rays at
    azimuth a from x = 0.125 m meet it 0.5 m / cos(a) too far: 0.50, 0.78, 1.46, 2.88, 4.78 m at
    0, 50, 70, 80, 84 deg. One ray behind meets a pedestrian wall the prediction calls other; one ray up meets
    nothing in the truth (a predicted floater there does not count)."""
    truth = np.zeros(WIDE.shape, np.uint8)
    truth[48:50] = VEHICLE
    truth[16:18] = PEDESTRIAN  # x in [-4, -3.5)
    pred = np.zeros_like(truth)
    pred[50:52] = VEHICLE
    pred[16:18] = OTHER
    pred[32, 512 // 2, 12] = VEHICLE  # floater straight above the origin
    dirs = np.concatenate([_horizontal(AZIMUTHS_DEG), _horizontal([180.0]), [[0.0, 0.0, 1.0]]])
    t_labels, t_depths = cast_rays(truth, ORIGIN, dirs, WIDE)
    p_labels, p_depths = cast_rays(pred, ORIGIN, dirs, WIDE)
    assert t_labels.tolist() == [VEHICLE] * 5 + [PEDESTRIAN, 0]
    assert p_labels.tolist() == [VEHICLE] * 5 + [OTHER, VEHICLE]
    cos = np.cos(np.radians(AZIMUTHS_DEG))
    assert np.allclose(t_depths[:5], 3.875 / cos) and np.allclose(p_depths[:5], 4.375 / cos)
    assert t_depths[5] == pytest.approx(3.625) and np.isinf(t_depths[6]) and p_depths[6] == pytest.approx(0.875)

    counts = ray_counts(p_labels, p_depths, t_labels, t_depths)
    result = ray_iou(counts, [VEHICLE, PEDESTRIAN, OTHER, BARRIER])
    # vehicle: 5 true rays, 5 predicted, tp 2 / 3 / 4 within 1 / 2 / 4 m -> tp / (10 - tp)
    for threshold, tp in ((1.0, 2), (2.0, 3), (4.0, 4)):
        assert result["per_class"][threshold][VEHICLE] == pytest.approx(tp / (10 - tp))
        assert result["per_class"][threshold][PEDESTRIAN] == 0.0 and result["per_class"][threshold][OTHER] == 0.0
        assert np.isnan(result["per_class"][threshold][BARRIER])
        assert result["miou"][threshold] == pytest.approx(tp / (10 - tp) / 3)
    assert result["rayiou"] == pytest.approx((2 / 8 + 3 / 7 + 4 / 6) / 9)
    assert result["n_rays"] == 6
    assert (counts + counts).tp.tolist() == (2 * counts.tp).tolist()


def test_identical_grids_score_one_with_the_full_pattern():
    sem = street_scene()
    origins = ray_origins(np.stack([np.eye(4)] * 3), 1, DEFAULT_GRID)
    labels, depths = cast_rays(sem, origins, ray_directions(), DEFAULT_GRID)
    result = ray_iou(ray_counts(labels, depths, labels, depths), sorted(set(np.unique(sem).tolist()) - {0}))
    assert result["rayiou"] == 1.0 and result["n_rays"] > 0.5 * len(labels)
    shifted = street_scene(shift_m=3.0)  # the cars 3 m further along x
    p_labels, p_depths = cast_rays(shifted, origins, ray_directions(), DEFAULT_GRID)
    moved = ray_iou(ray_counts(p_labels, p_depths, labels, depths), [VEHICLE])
    assert 0.0 < moved["miou"][1.0] < moved["miou"][4.0] < 1.0
