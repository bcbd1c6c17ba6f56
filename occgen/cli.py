"""`occgen` command line: train the VAE / DiT, sample (bev | expand | forecast), run the VAE bench."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Optional

import torch
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from nuplan_occ.cli.errors import CliApp
from nuplan_occ.dataset import open_dataset
from occgen.data import NoClipsError
from occgen.exr import MapFileError
from occgen.lidar_metrics import SweepSetError

app = CliApp("occgen", extra_errors=(MapFileError, SweepSetError, NoClipsError), no_args_is_help=True,
             help="Occupancy generation (UniScene v2 style): VAE, DiT, expansion, forecasting.")
console = Console()


def _progress() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("{task.fields[info]}"), console=console)


@app.command()
def train(
    what: str = typer.Argument(..., help="vae or dit"),
    data: Path = typer.Option(..., help="Dataset root."),
    out: Path = typer.Option(..., help="Checkpoint directory (vae.pt, dit_<task>.pt)."),
    config: str = typer.Option("tiny", help="tiny, tiny512, c32, c512"),
    steps: int = typer.Option(100, min=1),
    crop: Optional[int] = typer.Option(64, help="Random x/y crop in cells (0: full grid)."),
    task: str = typer.Option("spatial", help="DiT task: spatial (layout-conditioned) or temporal (forecasting)."),
    subset: Optional[str] = typer.Option(None, help="Dataset subset: spatial or temporal (manifest speeds)."),
    seed: int = typer.Option(0),
    threads: int = typer.Option(0, help="torch threads (0: torch default)."),
    clip_len: Optional[int] = typer.Option(None, min=1, help="vae: frames per training clip (consecutive output "
                                           "frames; default: the config's, 1). A DiT's clip follows its task."),
) -> None:
    """Train the VAE, or a DiT on the VAE already in --out."""
    from occgen import checkpoint
    from occgen.configs import CLASS_IDS, get_config
    from occgen.data import open_clips, semantics_batches
    from occgen.train import clip_len_for, train_dit, train_vae

    if what not in ("vae", "dit"):
        raise typer.BadParameter(f"{what!r}: train vae or dit")
    if clip_len is not None and what != "vae":
        raise typer.BadParameter("--clip-len is for the VAE; a DiT's clip length follows its task and config")
    if threads:
        torch.set_num_threads(threads)
    cfg = get_config(config)
    if clip_len is not None:
        cfg = replace(cfg, clip_len=clip_len)
    clips = open_clips(str(data), clip_len_for(cfg, "vae" if what == "vae" else task), subset)
    batches = semantics_batches(clips, cfg.batch_size, crop or None, torch.Generator().manual_seed(seed))
    with _progress() as progress:
        bar = progress.add_task(f"train {what}", total=steps, info="")

        def on_step(step: int, record: dict) -> None:
            progress.update(bar, completed=step, info=" ".join(f"{k} {v:.4f}" for k, v in record.items()))

        if what == "vae":
            depth = open_dataset(str(data)).grid.shape[2]
            vae, history = train_vae(batches, cfg, depth, steps, seed, on_step)
            checkpoint.save(out / checkpoint.VAE_FILE, vae,
                            {"config": config, "depth": depth, "class_ids": list(CLASS_IDS),
                             "clip_len": cfg.clip_len})
            losses = [h["total"] for h in history]
        else:
            vae = checkpoint.load_vae(out)
            if vae.cfg != cfg.vae:
                raise typer.BadParameter(f"{out}/vae.pt was trained with another VAE config than {config!r}")
            dit, scale, losses = train_dit(batches, vae, cfg, steps, task, seed, on_step)
            checkpoint.save(out / checkpoint.dit_file(task), dit, {"config": config, "latent_scale": scale})
    name = "vae" if what == "vae" else f"dit_{task}"
    (out / f"{name}_losses.json").write_text(json.dumps(losses))
    console.print(f"{name}: loss {losses[0]:.4f} -> {losses[-1]:.4f}; checkpoint in {out}")


@app.command()
def sample(
    data: Path = typer.Option(..., help="Dataset root (layouts / context frames come from it)."),
    ckpt: Path = typer.Option(..., help="Checkpoint directory."),
    mode: str = typer.Option("bev", help="bev, expand or forecast"),
    out: Path = typer.Option(..., help="Output dataset root (400 x 400 x 32 frames)."),
    crop: int = typer.Option(64, help="Generated crop size in cells (x and y)."),
    count: int = typer.Option(1, min=1, help="Number of scenes."),
    steps: int = typer.Option(50, min=1, help="DDIM steps."),
    guidance: float = typer.Option(1.0, help="Classifier-free guidance scale."),
    tiles: int = typer.Option(3, min=0, help="expand: outpainted windows (half a tile along +x each)."),
    frames: int = typer.Option(13, min=1, help="forecast: total frames of the roll-out."),
    seed: int = typer.Option(0),
) -> None:
    """Generate occupancy and write it as a dataset `nuplan-occ view` opens."""
    from occgen.export import write_scenes
    from occgen.sample import MODES, SampleOptions

    if mode not in MODES:
        raise typer.BadParameter(f"{mode!r}: mode is one of {sorted(MODES)}")
    opts = SampleOptions(crop, count, steps, guidance, tiles, frames, seed)
    with _progress() as progress:
        bar = progress.add_task(f"sample {mode}", total=count, info="")
        scenes = MODES[mode](str(data), str(ckpt), opts, lambda n, total: progress.update(bar, completed=n))
    n = write_scenes(str(out), scenes, {"occgen": {"mode": mode, "ckpt": str(ckpt), "source": str(data),
                                                    **opts.__dict__}})
    console.print(f"{n} frames of {len(scenes)} scenes written to {out}")


def _register_part2() -> None:
    """Camera maps and LiDAR generation commands (occgen part 2: render-maps, lidar, lidar-train, eval-lidar)."""
    from occgen.cli_sensors import register

    register(app)


_register_part2()


if __name__ == "__main__":
    app()
