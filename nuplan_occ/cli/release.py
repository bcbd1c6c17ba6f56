"""`nuplan-occ import-release`: the paper's released Nuplan-Occ into our dataset format. `register(app)` adds it."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

console = Console(stderr=True)


class ImportProgress:
    """One bar over the release folders and one over the files of the current folder."""

    def __init__(self, n_folders: int) -> None:
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), console=console)
        self.folders = self.progress.add_task("folders", total=n_folders)
        self.files = None
        self.counts = {"ok": 0, "failed": 0, "skipped": 0}

    def __enter__(self) -> "ImportProgress":
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def on_folder(self, folder) -> None:
        if self.files is not None:
            self.progress.remove_task(self.files)
            self.progress.advance(self.folders)
        self.files = self.progress.add_task(folder.name, total=len(folder.files))

    def on_frame(self, status: str) -> None:
        self.counts[status] += 1
        self.progress.advance(self.files)
        self.progress.update(self.folders, description=f"folders (ok {self.counts['ok']}, failed "
                                                       f"{self.counts['failed']}, skipped {self.counts['skipped']})")


def import_release_cmd(
    src: Path = typer.Argument(..., help="Release folder: holds dense_voxels_with_semantic/ or "
                           "nuplan_quantized_<X>_<Y>_<Z>/ (or is one of them)."),
    out: str = typer.Argument(..., help="Output dataset root (path or fsspec URL)."),
    layout: str = typer.Option("auto", "--layout", help="auto | sparse4 ([N,4] x,y,z,label) | sparse2 ([N,2] "
                               "flat index,label) | dense (nuplan_quantized .npy)."),
    z_min: float = typer.Option(-3.0, "--z-min", help="Lower z of the release grid, m: -3 (z in [-3, 5)); -5 for "
                                "the mini split's r800_old (z in [-5, 3))."),
    frame: str = typer.Option("ego", "--frame", help="Frame of the release grids: ego | lidar (converted to ego "
                              "with the log's LiDAR extrinsic when --logs-root finds it, else kept and marked)."),
    logs_root: Optional[Path] = typer.Option(None, "--logs-root",
                                             help="nuPlan data root: fill log, scene, timestamps, poses by token."),
    labels: Optional[str] = typer.Option(None, "--labels", help="uniscene | raw-sparse | nuplan-occ | FILE.json "
                                         "(default: raw-sparse for sparse files, uniscene for dense)."),
    flat_order: str = typer.Option("xyz", "--flat-order", help="Flat index order of [N,2] files: xyz (C order "
                                   "over [x, y, z]) or zyx (x fastest, OpenScene's)."),
) -> None:
    """Convert the released Nuplan-Occ into shards + manifest; rerunning skips imported frames."""
    from nuplan_occ.release.errors import ReleaseImportError
    from nuplan_occ.release.files import find_folders
    from nuplan_occ.release.importer import ImportOptions, import_release

    options = ImportOptions(layout=layout, z_min=z_min, frame=frame, labels=labels,
                            logs_root=str(logs_root) if logs_root else None, flat_order=flat_order)
    try:
        with ImportProgress(len(find_folders(src, layout))) as progress:
            summary = import_release(src, out, options, on_folder=progress.on_folder, on_frame=progress.on_frame)
    except ReleaseImportError as exc:
        console.print(f"[red]error[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(code=1)
    table = Table(title=f"import of {src}")
    table.add_column("what")
    table.add_column("frames", justify="right")
    for name in ("imported", "failed", "skipped"):
        table.add_row(name, str(getattr(summary, name)))
    for reason, count in summary.failure_reasons.most_common(10):
        table.add_row(f"  failed: {reason}", str(count))
    Console().print(table)
    if summary.imported == 0 and summary.skipped == 0:
        raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    """Add import-release to the main CLI app."""
    app.command("import-release")(import_release_cmd)
