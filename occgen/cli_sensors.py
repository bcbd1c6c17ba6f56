"""occgen part 2 commands (camera maps, LiDAR); `register(app)` adds them to a typer app.

    render-maps OUT --frames 0,1 --out DIR [--rig-db LOG.db] [--downscale 4] [--method ut|ewa]
    lidar-train OUT --ckpt FILE [--steps N]
    lidar OUT --out DIR [--model raycast|learned --ckpt FILE] [--frames ...] [--density 1.0]
    eval-lidar GEN REAL
OUT is a dataset root (nuplan_occ.dataset). Sweeps are written as `<DIR>/<token>.pcd`.
"""

from __future__ import annotations

import json

import typer

from nuplan_occ.dataset import open_dataset


def parse_frames(spec: str | None, n: int) -> list[int]:
    """"0,3,5" or "2:8" (python slice) or None (all) -> dataset indices; raises typer.BadParameter."""
    if spec is None:
        return list(range(n))
    try:
        if ":" in spec:
            return list(range(n))[slice(*(int(p) if p else None for p in spec.split(":")))]
        frames = [int(p) for p in spec.split(",") if p.strip()]
    except ValueError:
        raise typer.BadParameter(f"--frames {spec!r}: expected '0,1,2' or 'start:stop'") from None
    bad = [i for i in frames if not -n <= i < n]
    if bad:
        raise typer.BadParameter(f"--frames: indices {bad} out of range for {n} frames")
    return frames


def render_maps_cmd(
    out: str = typer.Argument(..., help="dataset root"),
    frames: str = typer.Option(None, help="'0,1,2' or 'start:stop' (default: all)"),
    dest: str = typer.Option(..., "--out", help="output folder"),
    rig_db: str = typer.Option(None, help="nuPlan log DB whose camera rows to use (default: synthetic rig)"),
    downscale: int = typer.Option(4, help="render at 1/downscale of the camera resolution"),
    method: str = typer.Option("ut", help="ut (unscented) or ewa (linearized)"),
) -> None:
    """Render per-camera depth/semantic EXR maps and PNG previews."""
    from occgen.render_maps import render_maps, rig_from_db

    cams = rig_from_db(rig_db) if rig_db else None
    paths = render_maps(out, parse_frames(frames, len(open_dataset(out))), dest, cams, downscale, method)
    typer.echo(f"wrote {len(paths)} EXR maps under {dest}")


def lidar_train_cmd(
    out: str = typer.Argument(..., help="dataset root"),
    ckpt: str = typer.Option(..., help="checkpoint file to write"),
    steps: int = typer.Option(3000),
    density: float = typer.Option(0.25, help="azimuth density of the training rig"),
) -> None:
    """Train the learned LiDAR model on the stand-in real sensor of every dataset frame."""
    from occgen.lidar_model import LidarModel, LidarModelConfig, dataset_frames, save_checkpoint, train
    from occgen.lidar_raycast import default_lidar_rig

    cfg, rig = LidarModelConfig(), default_lidar_rig(density)
    grid, _, _, frames = dataset_frames(out, list(range(len(open_dataset(out)))), rig, cfg)
    model = LidarModel(cfg)
    losses = train(model, frames, grid, rig, steps)
    save_checkpoint(model, ckpt)
    typer.echo(f"loss {losses[0]:.3f} -> {losses[-1]:.3f}; saved {ckpt}")


def lidar_cmd(
    out: str = typer.Argument(..., help="dataset root"),
    dest: str = typer.Option(..., "--out", help="output folder for PCD sweeps"),
    model: str = typer.Option("raycast", help="raycast or learned"),
    ckpt: str = typer.Option(None, help="checkpoint of the learned model (local file)"),
    frames: str = typer.Option(None, help="'0,1,2' or 'start:stop' (default: all)"),
    density: float = typer.Option(1.0, help="azimuth density of the rig"),
) -> None:
    """Generate nuPlan-format LiDAR sweeps from the occupancy of each frame."""
    from pathlib import Path

    from occgen.lidar_model import generate, load_checkpoint
    from occgen.lidar_raycast import default_lidar_rig, raycast_sweep, write_sweep

    if model not in ("raycast", "learned"):
        raise typer.BadParameter(f"--model {model!r}: use raycast or learned")
    if model == "learned" and not ckpt:
        raise typer.BadParameter("--model learned needs --ckpt")
    net = load_checkpoint(ckpt) if model == "learned" else None
    ds, rig = open_dataset(out), default_lidar_rig(density)
    indices = parse_frames(frames, len(ds))
    for i in indices:
        f = ds.get(i, keys=["semantics"])
        cloud = raycast_sweep(f["semantics"], ds.grid, rig) if net is None else generate(net, f["semantics"], ds.grid, rig)
        write_sweep(Path(dest) / f"{f['token']}.pcd", cloud)
    typer.echo(f"wrote {len(indices)} sweeps to {dest}")


def eval_lidar_cmd(gen: str = typer.Argument(...), real: str = typer.Argument(...)) -> None:
    """MMD / JSD (BEV histograms) and Chamfer distance between two folders of PCD sweeps (JSON)."""
    from occgen.lidar_metrics import eval_lidar

    typer.echo(json.dumps(eval_lidar(gen, real), indent=2))


def register(app: typer.Typer) -> None:
    """Add the part-2 commands to `app`."""
    app.command("render-maps")(render_maps_cmd)
    app.command("lidar-train")(lidar_train_cmd)
    app.command("lidar")(lidar_cmd)
    app.command("eval-lidar")(eval_lidar_cmd)
