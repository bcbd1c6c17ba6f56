"""VAE / DiT benchmarks on a dataset (by default a synthetic one), and the loss-curve PNG.

`run_vae_bench(data_root, steps, config)`: trains the config's VAE on the first 3/4 of the clips and
reports reconstruction IoU / mIoU (OccWorld definitions, see `occgen.metrics`) of the argmax decoding of
the encoder mean on the held-out last 1/4, the loss curve and the compression ratio.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from occgen.configs import compression_ratio, get_config
from occgen.data import load_clip, open_clips, semantics_batches
from occgen.export import GeneratedScene, translation, write_scenes
from occgen.metrics import OccupancyIoU
from occgen.synthetic import synthetic_scene
from occgen.train import StepCallback, clip_len_for, train_dit, train_vae
from occgen.vae import OccVAE

BENCH_GRID = GridSpec(x_min=-8.0, x_max=8.0, y_min=-8.0, y_max=8.0)
"""64 x 64 x 32 cells: the dataset z range, a 16 m x 16 m square around the ego."""


def make_synthetic_dataset(root: str, scenes: int = 4, frames: int = 8, grid: GridSpec = BENCH_GRID,
                           seed: int = 0) -> str:
    """Write `scenes` synthetic scenes (see `occgen.synthetic`) as a dataset; ego static, agents 5 m/s."""
    rng = np.random.default_rng(seed)
    items = [GeneratedScene(f"synthetic-{i:03d}", synthetic_scene(grid, frames, rng),
                            np.repeat(translation(np.array([100.0 * i, 0.0, 0.0]))[None], frames, 0),
                            {"ego_speed": 0.0, "max_agent_speed": 5.0})
             for i in range(scenes)]
    write_scenes(root, items, {"synthetic": True, "seed": seed}, grid=grid, zstd_level=1)
    return root


def split(n: int) -> tuple[list[int], list[int]]:
    """(train, held-out) clip indices: the last quarter (at least one clip) is held out."""
    if n < 2:
        raise ValueError(f"need at least 2 clips for a train / held-out split, got {n}")
    cut = n - max(n // 4, 1)
    return list(range(cut)), list(range(cut, n))


@torch.no_grad()
def evaluate_vae(vae: OccVAE, dataset, indices: list[int], crop: int | None) -> dict:
    """IoU / mIoU of argmax(decode(encoder mean)) against the centred crops of clips `indices`."""
    meter = OccupancyIoU()
    for index in indices:
        sem = load_clip(dataset, index, crop)[0][None]
        meter.update(vae.decode(vae.encode(sem)[0]), sem)
    return meter.compute()


def run_vae_bench(data_root: str, steps: int, config: str = "tiny", crop: int | None = None, seed: int = 0,
                  on_step: StepCallback | None = None) -> dict:
    """Train and evaluate a VAE; dict of iou, miou, per_class, losses (total per step), loss_terms,
    compression_ratio (H*W*D / h*w*C), latent_shape (C, h, w), config, steps, frames_train/held_out."""
    cfg = get_config(config)
    dataset = open_clips(data_root, clip_len=clip_len_for(cfg, "vae"))
    depth = open_dataset(data_root).grid.shape[2]
    train_idx, eval_idx = split(len(dataset))
    batches = semantics_batches(dataset, cfg.batch_size, crop, torch.Generator().manual_seed(seed), train_idx)
    vae, history = train_vae(batches, cfg, depth, steps, seed, on_step)
    metrics = evaluate_vae(vae, dataset, eval_idx, crop)
    size = crop or min(open_dataset(data_root).grid.shape[:2])
    d = cfg.vae.downsample
    return {
        "config": config, "steps": steps, **metrics,
        "compression_ratio": compression_ratio(cfg.vae, depth),
        "latent_shape": [cfg.vae.latent_channels, size // d, size // d],
        "clips_train": len(train_idx), "clips_held_out": len(eval_idx),
        "losses": [h["total"] for h in history], "loss_terms": history,
    }


def run_dit_bench(data_root: str, vae: OccVAE, steps: int, config: str = "tiny", task: str = "spatial",
                  crop: int | None = None, seed: int = 0) -> dict:
    """Train a DiT on a trained VAE; losses per step and the means of the first / last 10 % of steps."""
    cfg = get_config(config)
    dataset = open_clips(data_root, clip_len=clip_len_for(cfg, task))
    batches = semantics_batches(dataset, cfg.batch_size, crop, torch.Generator().manual_seed(seed))
    _, scale, losses = train_dit(batches, vae, cfg, steps, task, seed)
    k = max(steps // 10, 1)
    return {"config": config, "task": task, "steps": steps, "latent_scale": scale, "losses": losses,
            "loss_first": float(np.mean(losses[:k])), "loss_last": float(np.mean(losses[-k:]))}


def write_curve_png(curves: dict[str, list[float]], path: str | Path, title: str = "occgen training loss",
                    ylabel: str = "loss") -> None:
    """Plot named per-step curves (raw, and a moving average when long) to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, values in curves.items():
        values = np.asarray(values, dtype=float)
        line, = ax.plot(np.arange(1, len(values) + 1), values, alpha=0.35 if len(values) > 20 else 1.0,
                        label=None if len(values) > 20 else name)
        if len(values) > 20:
            k = max(len(values) // 20, 2)
            smooth = np.convolve(values, np.ones(k) / k, mode="valid")
            ax.plot(np.arange(k, len(values) + 1), smooth, color=line.get_color(), label=f"{name} (mean of {k})")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
