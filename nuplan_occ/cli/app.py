"""The `nuplan-occ` command line: build, synth, demo, summary (and the dataset tools)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console

from nuplan_occ.cli.errors import CliApp

app = CliApp("nuplan-occ", add_completion=False, no_args_is_help=True,
             help="Dense semantic occupancy grids from nuPlan logs (Nuplan-Occ style).")
console = Console(stderr=True)


def _build_params(config: Optional[Path], set_options: List[str], rate_hz: Optional[float]) -> dict:
    """The build's params: the stages' declared defaults, then the config file, then --rate-hz (only when
    given, so a config file's [load] rate_hz stands otherwise), then --set; each value checked as it is read."""
    from nuplan_occ.pipeline.params import apply_overrides, default_params, load_config_file, parse_set_options
    from nuplan_occ.stages import PIPELINE

    params = default_params(PIPELINE)
    if config is not None:
        params = apply_overrides(params, load_config_file(config), str(config))
    if rate_hz is not None:
        params = apply_overrides(params, {"load": {"rate_hz": rate_hz}}, "--rate-hz")
    return apply_overrides(params, parse_set_options(set_options), "--set")


@app.command()
def build(
    data_root: Path = typer.Argument(..., help="nuPlan data root (NUPLAN_DATA_ROOT layout)."),
    out: str = typer.Argument(..., help="Output dataset root: a path or an fsspec URL (s3://, memory://)."),
    split: str = typer.Option("mini", help="Split folder under nuplan-v1.1/splits ('' = every .db under the root)."),
    log: List[str] = typer.Option([], "--log", help="Only these logs (DB stems); repeatable."),
    maps_root: Optional[Path] = typer.Option(None, help="Maps root (default NUPLAN_MAPS_ROOT or DATA_ROOT/maps)."),
    rate_hz: Optional[float] = typer.Option(None, help="Output frame rate in Hz (default: load.rate_hz, 10; "
                                             "sweeps are 20 Hz)."),
    workers: int = typer.Option(1, min=1, help="Parallel scene workers."),
    executor: str = typer.Option("local", help="local (process pool) or ray."),
    ray_address: Optional[str] = typer.Option(None, help="Existing Ray cluster; default starts a local Ray."),
    config: Optional[Path] = typer.Option(None, help="JSON/TOML file of {stage: {param: value}} overrides."),
    set_option: List[str] = typer.Option([], "--set", help="STAGE.PARAM=VALUE override; repeatable."),
    strict: bool = typer.Option(False, help="Exit non-zero if any frame failed."),
    work_dir: Optional[Path] = typer.Option(None, help="Stage cache (default OUT/work, or a local cache folder for URLs)."),
    num_shards: int = typer.Option(1, help="Split the logs into this many build shards (by log name hash)..."),
    shard_index: int = typer.Option(0, help="...and build only this one (0-based; e.g. $SLURM_ARRAY_TASK_ID)."),
    keep_work: str = typer.Option("default", help="Stage cache kept after a scene is published: all, default "
                                  "(poses, boxes, surfaces, rows) or none."),
) -> None:
    """Build the occupancy dataset; rerunning skips finished work. Any number of builds may write into
    one OUT at once (other machines, other shards, the same logs)."""
    from nuplan_occ.pipeline.build import run_build
    from nuplan_occ.stages import PIPELINE
    from nuplan_occ.pipeline.publish import KEEP_WORK
    from nuplan_occ.progress import BuildProgress, summary_table

    params = _build_params(config, set_option, rate_hz)
    if keep_work not in KEEP_WORK or num_shards < 1 or not 0 <= shard_index < num_shards:
        console.print(f"error: need --keep-work in {KEEP_WORK} and 0 <= --shard-index < --num-shards "
                      f"(got {keep_work!r}, {shard_index}, {num_shards})", highlight=False)
        raise typer.Exit(code=2)
    with BuildProgress(console) as progress:
        summary = run_build(data_root, out, params, pipeline=PIPELINE, split=split or None, log_names=log or None,
                            maps_root=str(maps_root) if maps_root else None, workers=workers, executor=executor,
                            ray_address=ray_address, work_root=work_dir, num_shards=num_shards,
                            shard_index=shard_index, keep_work=keep_work, on_plan=progress.on_plan,
                            on_event=progress.on_event)
    console.print(summary_table(summary))
    for problem in summary.sensor_problems:
        console.print(f"no sensor metadata: {problem}", highlight=False, soft_wrap=True)
    if summary.frames_built == 0 or (strict and summary.frames_failed):
        raise typer.Exit(code=1)


@app.command()
def synth(
    out_root: Path = typer.Argument(..., help="Where to write the nuPlan data root and its truth."),
    logs: int = typer.Option(1, help="Number of logs."),
    seconds: float = typer.Option(10.0, help="Seconds per log."),
    seed: int = typer.Option(0, help="Random seed (same seed, same bytes)."),
    preset: str = typer.Option("small", help="small | city | small_objects | suburb"),
    imperfections: str = typer.Option("none", help="Imperfection profile: none | realistic (auto-label failures "
                                      "and sensor artefacts of real logs, each at its documented magnitude)."),
    location: str = typer.Option("us-nv-las-vegas-strip", help="us-nv-las-vegas-strip | us-pa-pittsburgh-hazelwood"),
    scene_seconds: Optional[float] = typer.Option(None, help="Scene length (default: the preset's, >= 5 scenes "
                                                  "per log); = --seconds makes one scene span the log."),
    truth_rate: float = typer.Option(20.0, help="Truth frames per second (20 / n)."),
    camera_rate: float = typer.Option(10.0, help="Camera images per second (20 / n; 0 = none)."),
    camera_mask: bool = typer.Option(False, help="Truth mask_camera (exact at the cameras' resolution; ~1 s per "
                                     "truth frame)."),
    preview: Optional[Path] = typer.Option(None, help="Write a PNG of one sweep over the truth grid."),
) -> None:
    """Write synthetic nuPlan logs from procedural worlds, with exact occupancy truth."""
    from nuplan_occ.synth.generate import synthesize
    from nuplan_occ.synth.presets import IMPERFECTIONS, imperfect_options
    from nuplan_occ.synth.preview import render_preview

    if imperfections not in IMPERFECTIONS:
        raise typer.BadParameter(f"{imperfections!r} is not one of {', '.join(IMPERFECTIONS)}",
                                 param_hint="--imperfections")

    synthesize(out_root, logs=logs, seconds=seconds, seed=seed, preset=preset, progress=console.log,
               scene_seconds=scene_seconds, truth_rate_hz=truth_rate, camera_rate_hz=camera_rate,
               camera_mask=camera_mask, options=imperfect_options(imperfections), location=location)
    if preview is not None:
        render_preview(out_root, preview)
        console.print(f"preview written to {preview}")


@app.command()
def summary(
    data_root: Path = typer.Argument(..., help="nuPlan data root."),
    split: str = typer.Option("mini", help="Split folder ('' = all)."),
) -> None:
    """Table of the logs under a data root: scenes, frames, boxes per category, points per LiDAR."""
    from nuplan_occ.io.data_root import resolve_logs, sensor_root_for
    from nuplan_occ.io.summary import render_summary, summarize_log

    rows = [summarize_log(db, sensor_root_for(db, data_root)) for db in resolve_logs(data_root, split=split or None)]
    Console().print(render_summary(rows))


@app.command()
def demo(
    out: Path = typer.Argument(Path("demo_out"), help="Folder for the synthetic data, the dataset and the picture."),
    seconds: float = typer.Option(4.0, help="Seconds of synthetic log."),
    workers: int = typer.Option(2, min=1, help="Parallel scene workers."),
) -> None:
    """Synthesize a log, build it, print the summary, write a picture of one frame and the build report."""
    from nuplan_occ.pipeline.build import run_build
    from nuplan_occ.stages import PIPELINE
    from nuplan_occ.progress import BuildProgress, summary_table
    from nuplan_occ.synth.generate import synthesize

    data_root = out / "data"
    if not (data_root / "nuplan-v1.1").exists():
        synthesize(data_root, logs=1, seconds=seconds, seed=0, preset="small", progress=console.log)
    params = _build_params(None, [], None)
    with BuildProgress(console) as progress:
        result = run_build(data_root, str(out / "dataset"), params, pipeline=PIPELINE, workers=workers,
                           on_plan=progress.on_plan, on_event=progress.on_event)
    console.print(summary_table(result))
    _demo_report(out)
    if result.frames_built == 0:
        raise typer.Exit(code=1)


def _demo_report(out: Path) -> None:
    """Quality of the demo build against the synthetic truth, a picture of one frame and the build report."""
    from nuplan_occ.evaluation.datasets import evaluate
    from nuplan_occ.report import write_report
    from nuplan_occ.viewer import render_frame

    result = evaluate(str(out / "dataset"), str(out / "data" / "truth"), json_path=out / "eval.json")
    pooled = result["pooled"]
    console.print(f"against the synthetic truth (inside its LiDAR mask, {result['frames_matched']} frames): "
                  f"IoU {pooled['iou']:.3f}, mIoU {pooled['miou']:.3f}; details in {out / 'eval.json'}")
    picture = out / "frame.png"
    render_frame(str(out / "dataset"), index=0, screenshot=picture)
    console.print(f"picture written to {picture}")
    report = write_report(str(out / "dataset"), out / "report")
    console.print(f"build report written to {report.index} (open it in a browser)")


def _register_dataset_tools() -> None:
    """view, eval, stats, validate, export, report, sensors, import-release, qa."""
    from nuplan_occ.cli import qa as cli_qa
    from nuplan_occ.cli import release as cli_release
    from nuplan_occ.cli.dataset import register

    register(app)
    cli_release.register(app)
    cli_qa.register(app)


_register_dataset_tools()


def main() -> None:
    app()

