"""Training, checkpoints, sampling and export against a small synthetic dataset on disk."""

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import ROAD, VEHICLE
from occgen import checkpoint
from benchmarks.occgen_bench import run_vae_bench, write_curve_png
from occgen.cli import app
from occgen.configs import get_config
from occgen.data import load_clip, open_clips, semantics_batches
from occgen.export import canvas_windows, place_in_grid


def test_batches_are_random_crops_of_dataset_clips(small_dataset):
    clips = open_clips(small_dataset, clip_len=2)
    batch = next(semantics_batches(clips, 3, 32, torch.Generator().manual_seed(0)))
    assert batch.shape == (3, 2, 32, 32, 8) and batch.dtype == torch.long
    sem, origin = load_clip(clips, 0, 32)
    assert origin == (16, 16)
    assert torch.equal(sem, clips[0]["semantics"][:, 16:48, 16:48].long())
    assert (sem[:, :, :, 4] > 0).all()  # the ground layer at z = 0 m
    with pytest.raises(ValueError, match="no clip"):
        open_clips(small_dataset, clip_len=50)


def test_vae_bench_learns_to_reconstruct(small_dataset, tmp_path):
    result = run_vae_bench(small_dataset, 40, "tiny", crop=32)
    assert result["compression_ratio"] == 4 * 4 * 8 / 16
    assert result["latent_shape"] == [16, 8, 8]
    losses = result["losses"]
    assert len(losses) == 40 and np.mean(losses[-5:]) < 0.6 * np.mean(losses[:5])
    assert result["iou"] > 0.7 and 0 <= result["miou"] <= 1
    write_curve_png({"tiny": losses}, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").read_bytes()[:4] == b"\x89PNG"


def test_place_in_grid_keeps_metric_position():
    sem = np.zeros((8, 8, 8), dtype=np.uint8)
    sem[0, 0, 0] = VEHICLE
    out = place_in_grid(sem, np.array([-8.0, -8.0, -1.0]), 0.25)
    assert out.shape == DEFAULT_GRID.shape
    idx, _ = DEFAULT_GRID.point_to_index(np.array([[-8.0 + 0.1, -8.0 + 0.1, -1.0 + 0.1]]))
    assert out[tuple(idx[0])] == VEHICLE and out.sum() == VEHICLE
    windows = canvas_windows(np.full((4, 4, 2), ROAD, np.uint8), np.array([49.5, 0.0, 0.0]), 0.25)
    assert len(windows) == 2 and windows[1][1][0, 3] == 100.0
    assert sum(int((f == ROAD).sum()) for f, _ in windows) == 4 * 4 * 2


def test_cli_train_sample_and_checkpoints(small_dataset, small_grid, tmp_path):
    runner = CliRunner()
    ck = tmp_path / "ck"
    common = ["--data", small_dataset, "--out", str(ck), "--steps", "3", "--crop", "32"]
    for args in (["train", "vae"], ["train", "dit"], ["train", "dit", "--task", "temporal"]):
        result = runner.invoke(app, args + common)
        assert result.exit_code == 0, result.output
    assert sorted(p.name for p in ck.glob("*.pt")) == ["dit_spatial.pt", "dit_temporal.pt", "vae.pt"]
    assert len(json.loads((ck / "vae_losses.json").read_text())) == 3
    vae = checkpoint.load_vae(ck)
    assert vae.depth == 8 and vae.cfg == get_config("tiny").vae
    with pytest.raises(ValueError, match="local"):
        checkpoint.load_vae("s3://bucket/ck")

    expected = {"bev": 2, "expand": 2, "forecast": 2 * 9}
    for mode, frames in expected.items():
        out = tmp_path / mode
        result = runner.invoke(app, ["sample", "--data", small_dataset, "--ckpt", str(ck), "--mode", mode,
                                     "--out", str(out), "--crop", "32", "--steps", "2", "--count", "2",
                                     "--frames", "9", "--tiles", "2"])
        assert result.exit_code == 0, result.output
        ds = open_dataset(str(out))
        assert len(ds) == frames and ds.grid == DEFAULT_GRID
        sem = ds[0]["semantics"]
        occupied = np.argwhere(sem > 0)
        # generated voxels stay inside the crop's (or the expanded canvas') metric footprint
        lo, _ = DEFAULT_GRID.point_to_index(small_grid.lower[None] + [4.0, 4.0, 0.0])
        assert occupied.size and (occupied.min(0) >= lo[0]).all()
        assert occupied[:, 2].max() < lo[0][2] + 8
    runner_bad = runner.invoke(app, ["sample", "--data", small_dataset, "--ckpt", str(ck), "--mode", "nope",
                                     "--out", str(tmp_path / "x")])
    assert runner_bad.exit_code != 0


def test_vae_trains_on_clips_and_the_bench_scores_the_same_held_out_frames_at_any_length(small_dataset, tmp_path):
    one = run_vae_bench(small_dataset, 2, "tiny", crop=32, clip_len=1)
    four = run_vae_bench(small_dataset, 2, "tiny", crop=32, clip_len=4)
    # 3 scenes x 8 frames: the last scene is held out; T = 4 trains on the 2 x 5 clips of the other scenes
    assert one["frames_held_out"] == four["frames_held_out"] == one["frames_scored"] == four["frames_scored"] == 8
    assert (one["clips_train"], four["clips_train"]) == (16, 10) and four["clip_len"] == 4
    result = CliRunner().invoke(app, ["train", "vae", "--data", small_dataset, "--out", str(tmp_path), "--steps", "1",
                                      "--crop", "32", "--clip-len", "4"])
    assert result.exit_code == 0, result.output
    assert torch.load(tmp_path / checkpoint.VAE_FILE, weights_only=True)["clip_len"] == 4
    result = CliRunner().invoke(app, ["train", "dit", "--data", small_dataset, "--out", str(tmp_path), "--clip-len", "2"])
    assert result.exit_code != 0 and "--clip-len is for the VAE" in result.output
