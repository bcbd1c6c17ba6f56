"""Rich progress display of a build: one bar over all scenes, one line per log with its current stage."""

from __future__ import annotations

from collections import Counter

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from nuplan_occ.pipeline.build import BuildSummary
from nuplan_occ.pipeline.scene import SceneTask


class BuildProgress:
    """Receives the build's plan and (log, scene, stage) events; use as a context manager."""

    def __init__(self, console: Console) -> None:
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), console=console, transient=False)
        self.overall = None
        self.per_log: dict[str, int] = {}

    def __enter__(self) -> "BuildProgress":
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def on_plan(self, tasks: list[SceneTask]) -> None:
        self.overall = self.progress.add_task("all scenes", total=len(tasks))
        for log_name, count in Counter(t.log_name for t in tasks).items():
            self.per_log[log_name] = self.progress.add_task(f"{log_name}: waiting", total=count)

    def on_event(self, event: tuple[str, str, str]) -> None:
        log_name, scene_name, stage = event
        task_id = self.per_log.get(log_name)
        if task_id is None:
            return
        if stage == "done":
            self.progress.advance(task_id)
            self.progress.advance(self.overall)
            self.progress.update(task_id, description=f"{log_name}: {scene_name} done")
        else:
            self.progress.update(task_id, description=f"{log_name}: {scene_name} [{stage}]")


def summary_table(summary: BuildSummary) -> Table:
    """The end-of-build table: frames, failures with reasons, time per stage, bytes per frame."""
    table = Table(title="build summary", show_header=True)
    table.add_column("what")
    table.add_column("value", justify="right")
    table.add_row("frames built", str(summary.frames_built))
    table.add_row("frames failed", str(summary.frames_failed))
    for reason, count in summary.failure_reasons.most_common(10):
        table.add_row(f"  failed: {reason}", str(count))
    table.add_row("scenes (failed / fully cached)",
                  f"{summary.scenes} ({summary.scenes_failed} / {summary.scenes_fully_cached})")
    for stage, seconds in summary.stage_seconds.items():
        table.add_row(f"time {stage}", f"{seconds:.1f} s")
    table.add_row("wall time", f"{summary.wall_seconds:.1f} s")
    table.add_row("bytes per frame", f"{summary.bytes_per_frame / 1024:.1f} KiB")
    table.add_row("peak RSS per worker", f"{summary.peak_rss_mb:.0f} MiB")
    return table
