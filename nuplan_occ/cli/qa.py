"""`nuplan-occ qa`: ray consistency of a built dataset against its logs' LiDAR (nuplan_occ.evaluation.ray_qa),
written to OUT/qa/ and summarised with the flag rules. `register(app)` adds it."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

console = Console()
err_console = Console(stderr=True)


def _median(rows: list[dict], column: str) -> float:
    values = [r[column] for r in rows if r.get(column) is not None and np.isfinite(r[column])]
    return float(np.median(values)) if values else float("nan")


def qa_tables(result) -> list[Table]:
    """Summary (medians of the figures, sources, flags by rule) and the flagged scenes of a `QaResult`."""
    from nuplan_occ.evaluation.ray_qa import SCENE_RULE_SHARE
    from nuplan_occ.rays.frame_qa import FIGURES
    from nuplan_occ.rays.consistency import FLAG_RULES

    rows = result.rows
    scored = [r for r in rows if not r["qa_ray_problem"]]
    summary = Table(title=f"ray consistency of {len(scored)} of {len(rows)} frames (medians)")
    summary.add_column("figure")
    summary.add_column("median", justify="right")
    for column in FIGURES:
        summary.add_row(column, f"{_median(scored, column):.4f}")
    summary.add_row("returns scored per frame", f"{_median(scored, 'qa_ray_scored'):,.0f}")
    held_out = sum(r["qa_ray_sweep_in_background"] is False for r in scored)
    refined = sum(r["qa_ray_poses"] == "refined" for r in scored)
    summary.caption = (f"scored against the sweeps between output frames: {held_out} of {len(scored)} held out of "
                       f"the background the grid was built from; poses: {refined} refined, "
                       f"{len(scored) - refined} logged")
    rules = Table(title="flag rules")
    for name in ("rule", "when", "frames"):
        rules.add_column(name, justify="right" if name == "frames" else "left")
    for name, (field, comparison, threshold) in FLAG_RULES.items():
        count = sum(name in r["qa_ray_flags"].split(",") for r in scored)
        rules.add_row(name, f"qa_ray_{field} {comparison} {threshold:g}", f"{count:,}")
    rules.add_row("scene", f"more than {SCENE_RULE_SHARE:.0%} of its frames flagged",
                  f"{len(result.flagged_scenes)} scenes")
    unscored = len(rows) - len(scored)
    if unscored:
        rules.add_row("not scored", "no loaded sweep near the frame (qa_ray_problem)", f"{unscored:,}")
    tables = [summary, rules]
    if result.flagged_scenes:
        scenes = Table(title="flagged scenes")
        scenes.add_column("scene")
        scenes.add_column("frames flagged", justify="right")
        for scene, share in sorted(result.flagged_scenes.items(), key=lambda item: -item[1]):
            scenes.add_row(scene, f"{share:.0%}")
        tables.append(scenes)
    return tables


def qa_cmd(
    out: str = typer.Argument(..., help="Built dataset root (path or fsspec URL)."),
    data_root: Path = typer.Option(..., "--data-root", envvar="NUPLAN_DATA_ROOT",
                                   help="nuPlan data root the dataset was built from (its LiDAR is the referee)."),
    maps_root: Optional[Path] = typer.Option(None, help="Maps root (default NUPLAN_MAPS_ROOT or DATA_ROOT/maps)."),
    work_dir: Optional[Path] = typer.Option(None, help="The build's work folder (default OUT/work): its refined "
                                            "poses are used when it still holds them, else the logged poses."),
    max_rays: int = typer.Option(20000, "--max-rays", min=1, help="Returns scored per frame at most."),
    force: bool = typer.Option(False, "--force", help="Score every scene again, even where OUT/qa is current."),
) -> None:
    """Ray consistency of every ok frame: the share of a nearby sweep's returns the grid agrees with, that end
    early (floaters, ghosts, trails), that meet a hole; written to OUT/qa/ray_consistency/ (one Parquet file
    per scene, keyed by token; the published shards and manifest are not touched); flags by stated rules."""
    from rich.progress import Progress

    from nuplan_occ.evaluation.ray_qa import QA_FOLDER, qa_dataset
    from nuplan_occ.stages import PIPELINE

    with Progress(console=err_console, transient=True) as progress:
        task = progress.add_task("qa", total=None)
        result = qa_dataset(out, data_root, PIPELINE, maps_root=str(maps_root) if maps_root else None,
                            work_root=work_dir, max_rays=max_rays, force=force,
                            progress=lambda done, total, scene: progress.update(
                                task, completed=done, total=total, description=scene))
    for table in qa_tables(result):
        console.print(table)
    console.print(f"{result.scored} scenes scored, {result.reused} unchanged; rows in {out}/{QA_FOLDER}/",
                  highlight=False, soft_wrap=True)
    if not result.rows:
        err_console.print(f"no ok frame of {out} was found under {data_root}")
        raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    """Add qa to the main CLI app."""
    app.command("qa")(qa_cmd)
