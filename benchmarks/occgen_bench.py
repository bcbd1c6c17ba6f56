"""VAE / DiT benchmarks on a dataset (by default a synthetic one), and the loss-curve PNG.

`run_vae_bench(data_root, steps, config, clip_len=T)`: trains the config's VAE on clips of T frames that
lie outside the held-out scenes (the last whole scenes within a quarter of the frames) and reports
reconstruction IoU / mIoU (OccWorld definitions, see `occgen.metrics`) of the argmax decoding of the
encoder mean on the held-out scenes (each frame decoded within a clip of T of their frames, so different
T score the same frames), the loss curve and the compression ratio.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.torch import OccupancyDataset
from occgen.configs import compression_ratio, get_config
from occgen.data import load_clip, open_clips, semantics_batches
from occgen.export import GeneratedScene, translation, write_scenes
from occgen.metrics import OccupancyIoU
from occgen.synthetic import synthetic_scene
from occgen.train import StepCallback, clip_len_for, train_vae
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


def held_out_split(data_root: str, dataset: OccupancyDataset) -> tuple[list[int], list[tuple[int, list[int]]], int]:
    """Hold out the last whole scenes (clip order: scene, output_index) that fit in a quarter of the frames
    (at least one scene; at least one stays for training), whatever the clip length.

    Returns (training clips: the clips of `dataset` in the other scenes; evaluation plan: (clip, positions in
    the clip) pairs of held-out clips that score each held-out frame once; number of held-out frames). A
    held-out frame in a run shorter than the clip length is in no plan entry."""
    frames = OccupancyDataset(data_root, clip_len=1)
    rows = [int(frames.frame_indices(i)[0]) for i in range(len(frames))]
    scene_of = frames.ds.manifest["scene_token"].to_pylist()
    scenes = list(dict.fromkeys(scene_of[r] for r in rows))
    if len(scenes) < 2:
        raise ValueError(f"{data_root}: need at least 2 scenes for a train / held-out split, got {len(scenes)}")
    size = {s: sum(scene_of[r] == s for r in rows) for s in scenes}
    held_scenes = {scenes[-1]}
    for scene in reversed(scenes[1:-1]):
        if sum(size[s] for s in held_scenes) + size[scene] > len(rows) / 4:
            break
        held_scenes.add(scene)
    held = {r for r in rows if scene_of[r] in held_scenes}
    train, plan, scored = [], [], set()
    for i in range(len(dataset)):
        clip = [int(r) for r in dataset.frame_indices(i)]
        if not held.intersection(clip):
            train.append(i)
        elif not scored.issuperset(clip):
            plan.append((i, [t for t, r in enumerate(clip) if r not in scored]))
            scored.update(clip)
    return train, plan, len(held)


@torch.no_grad()
def evaluate_vae(vae: OccVAE, dataset: OccupancyDataset, plan: list[tuple[int, list[int]]], crop: int | None) -> dict:
    """IoU / mIoU of argmax(decode(encoder mean)) of whole clips against their centred crops, scored on the
    frames `plan` names ((clip, positions) pairs, see `held_out_split`)."""
    meter = OccupancyIoU()
    for index, positions in plan:
        sem = load_clip(dataset, index, crop)[0][None]
        meter.update(vae.decode(vae.encode(sem)[0])[:, positions], sem[:, positions])
    return meter.compute()


def run_vae_bench(data_root: str, steps: int, config: str = "tiny", crop: int | None = None, seed: int = 0,
                  on_step: StepCallback | None = None, clip_len: int | None = None) -> dict:
    """Train and evaluate a VAE on clips of `clip_len` frames (default: the config's); dict of iou, miou,
    per_class, losses (total per step), loss_terms, compression_ratio (H*W*D / h*w*C), latent_shape
    (C, h, w), config, clip_len, steps, clips_train, frames_held_out, frames_scored."""
    cfg = get_config(config)
    if clip_len is not None:
        cfg = replace(cfg, clip_len=clip_len)
    dataset = open_clips(data_root, clip_len=clip_len_for(cfg, "vae"))
    depth = open_dataset(data_root).grid.shape[2]
    train_idx, plan, held_out = held_out_split(data_root, dataset)
    batches = semantics_batches(dataset, cfg.batch_size, crop, torch.Generator().manual_seed(seed), train_idx)
    vae, history = train_vae(batches, cfg, depth, steps, seed, on_step)
    metrics = evaluate_vae(vae, dataset, plan, crop)
    size = crop or min(open_dataset(data_root).grid.shape[:2])
    d = cfg.vae.downsample
    return {
        "config": config, "clip_len": cfg.clip_len, "steps": steps, **metrics,
        "compression_ratio": compression_ratio(cfg.vae, depth),
        "latent_shape": [cfg.vae.latent_channels, size // d, size // d],
        "clips_train": len(train_idx), "frames_held_out": held_out,
        "frames_scored": sum(len(positions) for _, positions in plan),
        "losses": [h["total"] for h in history], "loss_terms": history,
    }


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


def main(argv: list[str] | None = None) -> None:
    """`python -m benchmarks.occgen_bench --out DIR [--data ROOT] ...`: VAE reconstruction bench (IoU / mIoU on
    held-out frames, loss curves, compression ratios) of each config, written to DIR/bench.json and
    DIR/vae_loss.png."""
    import argparse
    import json

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--out", type=Path, required=True, help="bench.json, the curve PNG and a synthetic dataset")
    parser.add_argument("--data", type=Path, default=None, help="dataset root (default: a synthetic one in --out)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--config", action="append", default=None, help="configs to compare (default tiny, tiny512)")
    parser.add_argument("--crop", type=int, default=None, help="x/y crop in cells (default: the full grid)")
    parser.add_argument("--clip-len", type=int, action="append", default=[],
                        help="clip lengths T to compare (default: each config's own); results are named <config>@T<T>")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    configs = args.config or ["tiny", "tiny512"]
    root = str(args.data) if args.data is not None else make_synthetic_dataset(str(args.out / "synthetic"))
    runs = [(name, None, name) for name in configs] if not args.clip_len else [
        (name, t, f"{name}@T{t}") for name in configs for t in args.clip_len]
    results = {label: run_vae_bench(root, args.steps, name, args.crop, args.seed, clip_len=t) for name, t, label in runs}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench.json").write_text(json.dumps(results, indent=1))
    write_curve_png({f"{k} (ratio {v['compression_ratio']:g})": v["losses"] for k, v in results.items()},
                    args.out / "vae_loss.png", "occgen VAE training loss (CE + Lovasz + KL)")
    for label, r in results.items():
        print(f"{label}: ratio {r['compression_ratio']:g}, IoU {r['iou']:.3f}, mIoU {r['miou']:.3f} "
              f"on {r['frames_scored']} held-out frames, loss {r['losses'][0]:.3f} -> {r['losses'][-1]:.3f}")


if __name__ == "__main__":
    main()
