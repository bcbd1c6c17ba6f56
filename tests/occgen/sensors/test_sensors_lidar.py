import numpy as np
import pytest
import torch

from nuplan_occ.io.pcd import read_pcd
from nuplan_occ.labels import BARRIER
from occgen.lidar_metrics import SweepSetError, bev_histogram, chamfer, eval_lidar, jsd, mmd
from occgen.lidar_model import LidarModel, LidarModelConfig, generate, load_checkpoint, make_frame, save_checkpoint, train
from occgen.lidar_sampling import GROUPS, first_hit_pdf, occupancy_prior_samples, point_cues
from occgen.lidar_raycast import (SensorEffects, VoxelRaycaster, default_lidar_rig, raycast_sweep, scan, write_sweep)
from occgen.video_cond import load_local_state


def test_raycast_hits_a_wall_at_its_known_distance(small_grid):
    sem = np.zeros(small_grid.shape, np.uint8)
    sem[100, :, :] = BARRIER  # wall face at x = 9.0 m (voxel x in [9, 9.25))
    caster = VoxelRaycaster(sem, small_grid)
    origins = np.array([[1.52, 0.0, 1.9], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    dirs = np.array([[1.0, 0.0, 0.0], [np.cos(0.3), np.sin(0.3), 0.0], [-1.0, 0.0, 0.0]])
    t, label, _ = caster.cast(origins, dirs)
    assert t[0] == pytest.approx(9.0 - 1.52, abs=1e-4)
    assert t[1] == pytest.approx(9.0 / np.cos(0.3), abs=1e-4)
    assert np.isinf(t[2]) and label[2] == 0
    assert label[0] == label[1] == BARRIER
    top = scan(caster, default_lidar_rig(0.25)[0])
    fwd = top.range[:, top.spec.azimuth_steps // 2]  # the middle azimuth is straight ahead; range = (9 - 1.52) / cos(elevation) where it hits
    elev = np.radians(np.asarray(top.spec.elevations_deg))
    hit = np.isfinite(fwd)
    assert hit.sum() > 30
    assert np.allclose(fwd[hit], (9.0 - 1.52) / np.cos(elev[hit]), atol=1e-3)


def test_sweep_round_trips_through_pcd(tmp_path, small_grid, street):
    cloud = raycast_sweep(street, small_grid, default_lidar_rig(0.1))
    assert set(np.unique(cloud.lidar_info)) == {0, 1, 2, 3, 4}
    write_sweep(tmp_path / "s.pcd", cloud)
    back = read_pcd((tmp_path / "s.pcd").read_bytes(), "s.pcd")
    assert back.frame == "lidar" and len(back) == len(cloud)
    assert np.allclose(back.xyz, cloud.xyz, atol=1e-4)
    assert np.array_equal(back.lidar_info, cloud.lidar_info) and np.array_equal(back.ring, cloud.ring)
    assert np.allclose(back.intensity, cloud.intensity, atol=1e-6)


def test_metrics_known_values(tmp_path, small_grid, street):
    a = np.array([[0.5, 0.5, 0.0], [10.5, 0.5, 0.0]])
    assert chamfer(a, a) == 0.0
    assert chamfer(a, a + [0.0, 0.0, 1.0]) == pytest.approx(2.0)
    h = bev_histogram(a)
    assert h.sum() == pytest.approx(1.0) and h[50, 50] == 0.5
    hs = h[None]
    assert jsd(hs, hs) == 0.0 and mmd(hs, hs) == 0.0
    disjoint = bev_histogram(a + [20.0, 0.0, 0.0])[None]
    assert jsd(hs, disjoint) == pytest.approx(np.log(2.0))
    clean = raycast_sweep(street, small_grid, default_lidar_rig(0.1))
    noisy = raycast_sweep(street, small_grid, default_lidar_rig(0.1), SensorEffects(seed=1))
    write_sweep(tmp_path / "g" / "x.pcd", clean)
    write_sweep(tmp_path / "r" / "x.pcd", noisy)
    out = eval_lidar(tmp_path / "g", tmp_path / "r")
    assert out["n_paired"] == 1 and 0 < out["chamfer_m"] < 0.5 and out["jsd"] < 0.05
    with pytest.raises(SweepSetError):
        eval_lidar(tmp_path / "empty", tmp_path / "r")


def test_learned_lidar_model_trains_and_generates(tmp_path, small_grid, street):
    rig = default_lidar_rig(0.125)
    cfg = LidarModelConfig(far=40.0)
    frame = make_frame(street, small_grid, rig, cfg, SensorEffects())
    model = LidarModel(cfg)
    losses = train(model, [frame], small_grid, rig, steps=40, n_patches=48)
    assert np.mean(losses[-8:]) < 0.6 * np.mean(losses[:8])
    save_checkpoint(model, tmp_path / "m.pt")
    again = load_checkpoint(tmp_path / "m.pt")
    cloud = generate(again, street, small_grid, rig)
    assert len(cloud) > 100 and set(np.unique(cloud.lidar_info)) <= {0, 1, 2, 3, 4}
    ranges = np.linalg.norm(cloud.xyz - np.array([rig[i].position_ego for i in cloud.lidar_info]), axis=1)
    assert ranges.min() >= 1.0 and ranges.max() <= 40.0
    with torch.no_grad():
        again.head[-1].bias[1] = 30.0  # drop probability ~1: every ray is dropped
    assert len(generate(again, street, small_grid, rig)) == 0
    with pytest.raises(ValueError):
        load_local_state("https://example.com/m.pt")


def test_adaln_zero_blocks_start_as_identity():
    model = LidarModel(LidarModelConfig())
    x = torch.randn(1, 16, 4, 4, 2)
    f_r = model.rig_embedding(torch.randn(5, 3), torch.tensor([True, False, True, False, False]))
    assert torch.equal(model.blocks[0](x, f_r), x)


def test_occupancy_prior_samples_gather_at_the_visible_surface(small_grid):
    sem = np.zeros(small_grid.shape, np.uint8)
    sem[100, :, :] = BARRIER  # wall face at x = 9.0 m
    sem[110, :, :] = BARRIER  # a second wall behind it, hidden
    labels = torch.from_numpy(sem)
    o = torch.tensor([[1.0, 0.0, 0.1], [1.0, 0.0, 0.1]])
    d = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])  # towards the wall; away from it (a miss)
    s, free = occupancy_prior_samples(labels, small_grid, o, d, 32, 1.0, 40.0, 0.125, 2, 2, 0.25, jitter=False)
    assert torch.all(s[:, 1:] >= s[:, :-1]) and s.min() >= 1.0 and s.max() <= 40.0
    near = ((s[0] >= 7.625 - 1e-4) & (s[0] <= 8.25 + 1e-4)).float().mean()
    assert near >= 0.7  # surface at s = 8 m, first occupied march point; 75 % of the samples in 7.625..8.25
    assert (s[0] < 8.0).any() and (s[0] > 8.0).any()  # bracketed
    assert float(free[0]) == pytest.approx(7.875) and float(free[1]) == 40.0
    assert torch.allclose(torch.diff(s[1]), torch.full((31,), 39.0 / 32), atol=1e-3)  # uniform on a miss
    pdf = first_hit_pdf(torch.tensor([3, 6]), 6, 1, 0, 0.1)
    assert torch.equal(pdf[0], torch.tensor([0.1, 0.1, 1.0, 1.0, 0.1, 0.1])) and torch.all(pdf[1] == 1.0)


def test_point_cues_read_the_voxel_under_the_point(small_grid, street):
    labels = torch.from_numpy(street)
    pts = torch.tensor([[9.1, 0.0, 0.0], [0.0, 0.0, -0.4], [50.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    cues = point_cues(labels, small_grid, pts)
    assert torch.equal(cues[0, :5], GROUPS[6]) and torch.equal(cues[1, :5], GROUPS[12])
    assert torch.all(cues[2:, :5] == 0)  # outside the grid / free
    assert cues[1, :5].tolist() == [1.0, 1.0, 0.0, 0.0, 0.0]  # road: occupied, ground
    assert cues[0, 5] == pytest.approx((0.1 / 0.25) * 2 - 1, abs=1e-5)  # x = 9.1 m lies 0.4 into its voxel
