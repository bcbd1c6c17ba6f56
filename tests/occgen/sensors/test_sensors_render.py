from dataclasses import replace

import numpy as np
import pytest

from nuplan_occ.labels import BARRIER, VEHICLE
from occgen.exr import MapFileError, read_maps_exr
from occgen.gaussians import gaussians_from_occupancy
from occgen.render_maps import camera_pose, default_rig, downscaled, render_camera, render_maps
from occgen.unscented import project_points

import torch


def _camera(position, yaw=0.0, factor=4):
    return downscaled(replace(default_rig()[0], T_ego_from_camera=camera_pose(np.array(position), yaw)), factor)


def test_rendered_depth_of_a_wall_is_its_analytic_depth(small_grid):
    sem = np.zeros(small_grid.shape, np.uint8)
    sem[100, 20:108, 4:30] = BARRIER  # one voxel thick: centres at x = 9.125 m
    cam = _camera((0.0, 0.0, 1.0))
    maps = render_camera(gaussians_from_occupancy(sem, small_grid), cam)
    lit = maps["alpha"] > 0.5
    assert lit.sum() > 500
    assert np.all(maps["semantic"][lit] == BARRIER)
    assert np.abs(maps["depth"][lit] - 9.125).max() < 1e-4
    assert np.all(maps["semantic"][maps["alpha"] == 0] == 0)


def test_rendered_depth_of_a_car_box_front_face(small_grid):
    sem = np.zeros(small_grid.shape, np.uint8)
    sem[70:86, 40:50, 11:17] = VEHICLE  # x [1.5, 5.5), y [-6, -3.5), z [-0.25, 1.25)
    cam = _camera((-3.0, -4.75, 0.5))
    gs = gaussians_from_occupancy(sem, small_grid)
    maps = render_camera(gs, cam)
    front_depth = 1.625 + 3.0  # first layer of voxel centres, camera looking along +x
    lit = maps["alpha"] > 0.5
    assert np.all(maps["semantic"][lit] == VEHICLE)
    # every lit pixel sees a voxel centre at or behind the front layer
    assert maps["depth"][lit].min() > front_depth - 1e-3
    # at the pixels where the front-face centres project (exact camera model), depth is the front layer's
    front = gs.means[np.isclose(gs.means[:, 0], 1.625)]
    T = cam.T_ego_from_camera
    uv, ok = project_points(torch.from_numpy((front - T[:3, 3]) @ T[:3, :3]), cam.K, cam.distortion)
    px = np.round(uv[ok].numpy()).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    px = px[inside]
    assert len(px) > 50
    depth = maps["depth"][px[:, 1], px[:, 0]]
    assert np.all(maps["semantic"][px[:, 1], px[:, 0]] == VEHICLE)
    err = np.abs(depth - front_depth)
    assert np.quantile(err, 0.9) < 0.01
    # the rest mix in Gaussians of deeper layers (alpha is capped at 0.99 and a pixel centre is up to
    # 0.7 px from the projected centre), never more than the box allows
    assert err.max() < 0.6


def test_render_maps_writes_exr_and_png(tmp_path, street_dataset):
    root = street_dataset
    cams = default_rig()[:2]
    paths = render_maps(root, [0], tmp_path / "maps", cams, downscale=8)
    assert [p.name for p in paths] == ["CAM_F0.exr", "CAM_B0.exr"]
    maps = read_maps_exr(paths[0])
    assert maps["depth"].shape == (135, 240)
    assert (maps["alpha"] > 0).any() and set(np.unique(maps["semantic"])) <= {0, 2, 6, 12}
    assert (paths[0].parent / "CAM_F0.png").is_file()
    with pytest.raises(MapFileError):
        read_maps_exr(tmp_path / "missing.exr")
