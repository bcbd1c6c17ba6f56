"""Dataset tools of the `nuplan-occ` CLI: view, eval, stats, validate, export, sensors, compact, report. `register(app)` adds
them."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

console = Console()
err_console = Console(stderr=True)


def _fmt(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return "n/a" if value != value else f"{value:.{digits}f}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


def view_cmd(
    out: str = typer.Argument(..., help="Dataset root (path or fsspec URL)."),
    index: Optional[int] = typer.Option(None, "--index", help="Frame index among the ok frames (default 0)."),
    token: Optional[str] = typer.Option(None, "--token", help="lidar_pc token of the frame (instead of --index)."),
    mask: Optional[str] = typer.Option(None, "--mask", help="lidar | camera: draw only voxels inside that mask."),
    unknown: bool = typer.Option(False, "--unknown", help="With --mask: draw the unobserved space translucent."),
    points: bool = typer.Option(False, "--points", help="Overlay the frame's LiDAR sweep, read from --data-root "
                                "(skipped with a message when the log or its blobs are not reachable)."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", envvar="NUPLAN_DATA_ROOT",
                                             help="nuPlan data root holding the source logs (for --points)."),
    screenshot: Optional[Path] = typer.Option(None, "--screenshot", help="Render off-screen to this PNG."),
) -> None:
    """Show one frame in 3D: voxels in the label palette, the ego box, optional mask and LiDAR points."""
    from nuplan_occ.dataset import open_dataset
    from nuplan_occ.viewer import PointsUnavailable, frame_points_ego, render_frame

    if index is not None and token is not None:
        raise typer.BadParameter("give --index or --token, not both")
    if mask not in (None, "lidar", "camera"):
        raise typer.BadParameter("--mask must be lidar or camera")
    ds = open_dataset(out)
    i = ds.index_of_token(token) if token is not None else (index or 0)
    cloud = None
    if points:
        ident = ds.get(i, keys=())
        if data_root is None:
            err_console.print("--points skipped: no --data-root given (or NUPLAN_DATA_ROOT set)")
        else:
            try:
                cloud = frame_points_ego(data_root, ident["log_name"], ident["token"])
            except PointsUnavailable as exc:
                err_console.print(f"--points skipped: source sweep not reachable: {exc}")
    render_frame(out, index=i, mask=mask, points=cloud, screenshot=screenshot, show_unknown=unknown)
    if screenshot is not None:
        console.print(f"screenshot written to {screenshot}")


def eval_table(result: dict) -> Table:
    """Rich table of an `evaluate` result: pooled IoU and per-class IoU."""
    pooled = result["pooled"]
    table = Table(title=f"{result['frames_matched']} matched frames (built {result['frames_built']}, "
                        f"truth {result['frames_truth']}), mask: {result['mask']}")
    table.add_column("class")
    table.add_column("IoU", justify="right")
    table.add_row("[bold]occupied[/bold]", _fmt(pooled["iou"]))
    for class_id, iou in pooled["per_class"].items():
        table.add_row(f"{result['class_names'][class_id]} ({class_id})", _fmt(iou))
    table.add_row("[bold]mIoU[/bold]", _fmt(pooled["miou"]))
    table.add_row("mean per-frame IoU / mIoU", f"{_fmt(result['mean_frame_iou'])} / {_fmt(result['mean_frame_miou'])}")
    return table


FRAME_ROWS_SHOWN = 20


def frames_table(result: dict) -> Table:
    """Rich table of the first FRAME_ROWS_SHOWN per-frame rows of an `evaluate` result."""
    frames = result["frames"]
    more = f" (first {FRAME_ROWS_SHOWN}; all in --json)" if len(frames) > FRAME_ROWS_SHOWN else ""
    table = Table(title=f"per frame{more}")
    for name in ("token", "IoU", "mIoU", "occupied built", "occupied truth"):
        table.add_column(name, justify="left" if name == "token" else "right")
    for f in frames[:FRAME_ROWS_SHOWN]:
        table.add_row(f["token"], _fmt(f["iou"]), _fmt(f["miou"]), _fmt(f["n_occupied_built"]),
                      _fmt(f["n_occupied_truth"]))
    return table


def eval_cmd(
    built: str = typer.Argument(..., help="Built dataset root, or a folder of model predictions (per-token .npz "
                                "with key semantics or pred, or .npy; uint8 [x, y, z]): scored with the field's metrics."),
    truth: str = typer.Argument(..., help="Truth dataset root (frames matched by token)."),
    mask: Optional[str] = typer.Option(None, "--mask", help="Truth member restricting the voxels: mask_lidar, "
                                       "mask_camera or none (default mask_lidar; mask_camera for the field's metrics)."),
    field: bool = typer.Option(False, "--field", help="Score a built dataset with the field's metrics too "
                               "(Occ3D-style mIoU, RayIoU, F-score), as a prediction folder is."),
    pred_grid: Optional[str] = typer.Option(None, "--pred-grid", help="Grid of the prediction files: ours (default), "
                                            "occ3d, or x_min,x_max,y_min,y_max,z_min,z_max,voxel_size (m)."),
    pred_labels: str = typer.Option("ours", "--pred-labels", help="Label ids of the prediction files: ours, or "
                                    "occ3d (as `export --format occ3d` writes them, free = 17)."),
    rays: bool = typer.Option(True, "--rays/--no-rays", help="Compute RayIoU (the slowest figure)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the full result (per-frame table) here."),
    picture: Optional[Path] = typer.Option(None, "--picture", help="PNG of one matched frame, top-down: built | "
                                           "truth | difference (e.g. an imported release against our build)."),
    token: Optional[str] = typer.Option(None, "--token", help="lidar_pc token of the --picture frame (default: "
                                        "the first matched frame)."),
) -> None:
    """IoU / per-class IoU / mIoU of a built dataset against a truth dataset, or the field's metrics of model
    predictions (Occ3D-style mIoU, RayIoU at 1 / 2 / 4 m, F-score); frames matched by token."""
    from nuplan_occ.evaluation.datasets import evaluate
    from nuplan_occ.evaluation.prediction_eval import is_dataset_root, evaluate_predictions

    if field or not is_dataset_root(built):
        from nuplan_occ.cli.field_eval import field_tables

        mask = mask or "mask_camera"
        result = evaluate_predictions(built, truth, mask=mask, pred_grid=pred_grid, labels=pred_labels, rays=rays,
                                      json_path=json_out)
        for table in field_tables(result):
            console.print(table)
        for key, what in (("truth_frames_without_prediction", "truth frames have no prediction"),
                          ("predictions_without_truth", "predictions have no truth frame"),
                          ("frames_without_mask", f"truth frames have no {mask}: scored everywhere")):
            if result[key]:
                err_console.print(f"{result[key]} {what}")
        if json_out is not None:
            console.print(f"JSON written to {json_out}")
        return
    mask = mask or "mask_lidar"
    result = evaluate(built, truth, mask=mask, json_path=json_out)
    console.print(eval_table(result))
    console.print(frames_table(result))
    if picture is not None:
        from nuplan_occ.release.compare import render_frame_pair

        token = token or result["frames"][0]["token"]
        render_frame_pair(built, truth, token, picture)
        console.print(f"picture of frame {token} written to {picture}")
    if result["frames_without_mask"]:
        err_console.print(f"{result['frames_without_mask']} truth frames have no {mask}: scored everywhere")
    if json_out is not None:
        console.print(f"JSON written to {json_out}")


def _number(value: float | None) -> str:
    """A QA figure in few characters: integral values as integers, others to 4 significant digits."""
    if value is None:
        return "-"
    if float(value).is_integer() and abs(value) < 1e12:
        return f"{int(value):,}"
    return f"{value:,.1f}" if abs(value) >= 1000 else f"{value:.4g}"


def qa_tables(qa: dict) -> list[Table]:
    """The QA columns as two narrow tables (numeric figures; flags and labels), each column name in
    full on one line: they fit an 80-column terminal for names up to ~30 characters."""
    numeric = {name: q for name, q in qa.items() if "fraction_true" not in q and "counts" not in q}
    other = {name: q for name, q in qa.items() if name not in numeric}
    width = max((len(name) for name in qa), default=6)
    tables = []
    if numeric:
        table = Table(title="QA columns, numeric (ok frames)")
        table.add_column("column", no_wrap=True, min_width=width)
        for name in ("n", "null", "median", "min", "max"):
            table.add_column(name, justify="right", overflow="fold")
        for column, q in numeric.items():
            table.add_row(column, _fmt(q["n"]), _fmt(q["null"]),
                          *(_number(q.get(k)) for k in ("median", "min", "max")))
        tables.append(table)
    if other:
        table = Table(title="QA columns, flags and labels (ok frames)")
        table.add_column("column", no_wrap=True, min_width=width)
        for name in ("n", "null"):
            table.add_column(name, justify="right")
        table.add_column("values", overflow="fold")
        for column, q in other.items():
            values = (f"{100 * q['fraction_true']:.1f}% true" if q.get("fraction_true") is not None
                      else ", ".join(f"{k or '(empty)'}: {v}" for k, v in q.get("counts", {}).items()) or "-")
            table.add_row(column, _fmt(q["n"]), _fmt(q["null"]), values)
        tables.append(table)
    return tables


def stats_tables(stats: dict) -> list[Table]:
    """Rich tables of a `dataset_stats` result."""
    frames = Table(title=f"frames of {stats['root']}")
    for name in ("total", "ok", "failed", "logs", "scenes"):
        frames.add_column(name, justify="right")
    frames.add_row(*(_fmt(stats["frames"][k]) for k in ("total", "ok", "failed", "logs", "scenes")))
    tables = [frames]
    if stats["failure_reasons"]:
        reasons = Table(title="failure reasons")
        reasons.add_column("reason")
        reasons.add_column("frames", justify="right")
        for reason, count in stats["failure_reasons"].items():
            reasons.add_row(reason, _fmt(count))
        tables.append(reasons)
    classes = Table(title="voxels per class (ok frames)")
    for name in ("id", "class", "voxels", "% of all", "% of occupied"):
        classes.add_column(name, justify="right" if name != "class" else "left")
    for c in stats["classes"]:
        occupied = "-" if c["fraction_of_occupied"] is None else f"{100 * c['fraction_of_occupied']:.2f}"
        classes.add_row(str(c["id"]), c["name"], _fmt(c["voxels"]), f"{100 * c['fraction']:.3f}", occupied)
    tables.append(classes)
    sizes = Table(title=f"stored bytes per frame (all members: {stats['bytes_per_frame']:,.0f} mean)")
    for name in ("member", "frames", "mean", "median", "max", "total"):
        sizes.add_column(name, justify="right" if name != "member" else "left")
    for member, b in stats["bytes"].items():
        sizes.add_row(member, _fmt(b["frames"]), f"{b['mean']:,.0f}", f"{b['median']:,.0f}", _fmt(b["max"]),
                      _fmt(b["total"]))
    tables.append(sizes)
    tables += qa_tables(stats["qa"])
    return tables


STRICT_HELP = "Refuse (exit 1) if a manifest file is unreadable, instead of skipping it with a warning."


def stats_cmd(out: str = typer.Argument(..., help="Dataset root."),
              strict: bool = typer.Option(False, "--strict", help=STRICT_HELP)) -> None:
    """Frames ok/failed, failure reasons, class totals, bytes per frame, QA columns (from the manifest); the
    unreadable manifest files skipped, and whose frames that leaves out, are listed last."""
    from nuplan_occ.stats import dataset_stats

    stats = dataset_stats(out, strict=strict)
    for table in stats_tables(stats):
        console.print(table)
    if stats["damaged"]:
        damaged = Table(title="unreadable manifest files (skipped; figures above exclude their rows)")
        for name in ("file", "shard", "what readers see"):
            damaged.add_column(name, overflow="fold")
        for d in stats["damaged"]:
            seen = {"superseded": "a newer commit (nothing missing)", "unreadable": "its frames are missing",
                    "fallback": f"earlier commit {d['fallback_commit']}"}[d["outcome"]]
            damaged.add_row(d["path"], d["shard_folder"] or "(any)", seen)
        console.print(damaged)


def validate_cmd(out: str = typer.Argument(..., help="Dataset root.")) -> None:
    """Check metadata, manifest (every file readable) and every stored member, the frames' json included;
    exit 1 if any problem is found."""
    from nuplan_occ.storage.validate import validate_dataset

    problems = validate_dataset(out)
    for problem in problems:
        console.print(f"[red]problem[/red] {problem}", highlight=False, soft_wrap=True)
    if problems:
        err_console.print(f"{len(problems)} problem(s) in {out}")
        raise typer.Exit(code=1)
    console.print(f"{out}: valid")


def export_cmd(
    out: str = typer.Argument(..., help="Dataset root."),
    dest: Path = typer.Argument(..., help="Destination folder (local)."),
    format: str = typer.Option(..., "--format", help="occ3d (gts/<scene>/<token>/labels.npz + occ_infos.pkl, free = 17), "
                               "uniscene (nuplan_quantized_X_Y_Z/<token>.npy + nuplan_infos.pkl, LiDAR frame) or mesh "
                               "(<log>/<scene>.glb and .ply)."),
    frame: Optional[str] = typer.Option(None, "--frame", help="ego | lidar: the grids' frame (default: occ3d ego, "
                                        "uniscene lidar; needs the dataset's sensor metadata)."),
    grid: Optional[str] = typer.Option(None, "--grid", help="occ3d (200 x 200 x 16 at 0.4 m) or a voxel size such as "
                                       "0.5m: coarsen (rules in export.json); default: the dataset's grid."),
    data_root: Optional[Path] = typer.Option(None, "--data-root", envvar="NUPLAN_DATA_ROOT",
                                             help="mesh: the nuPlan data root the dataset was built from."),
    token: Optional[str] = typer.Option(None, "--token", help="mesh: only this frame's scene, objects placed "
                                        "at this frame (default: every scene, at its first frame)."),
    strict: bool = typer.Option(False, "--strict", help=STRICT_HELP),
) -> None:
    """Write the ok frames as Occ3D-style labels.npz or UniScenev2-style dense .npy files, or each scene's
    reconstructed background and object surfaces as meshes (GLB for Blender, PLY for MeshLab). A frame that
    cannot be read is skipped with one line naming it and its member; the rest are written, then exit 1."""
    if format == "mesh":
        from nuplan_occ.export.meshes import export_meshes
        from nuplan_occ.stages import PIPELINE

        if data_root is None:
            raise typer.BadParameter("--format mesh needs --data-root (or NUPLAN_DATA_ROOT)")
        summary = export_meshes(out, dest, data_root, PIPELINE, token=token)
        meshes = sum(len(s["meshes"]) for s in summary["scenes"])
        console.print(f"{meshes} meshes of {len(summary['scenes'])} scenes exported to {dest} (scene frame); "
                      f"list in {dest / 'mesh_export.json'}")
        return
    from nuplan_occ.export.formats import export_dataset

    summary = export_dataset(out, dest, format, strict=strict, frame=frame, grid=grid)
    for warning in summary["warnings"]:
        err_console.print(f"warning: {warning}", highlight=False, soft_wrap=True)
    for skipped in summary["skipped"]:
        err_console.print(f"skipped frame {skipped['frame']}, member {skipped['member']}: {skipped['problem']}",
                          highlight=False, soft_wrap=True)
    console.print(f"{summary['frames']} frames exported to {dest} ({format}, {summary['frame']} frame, grid "
                  f"{summary['grid']['shape']}); info file {summary['info_file']}; remap and frame list in "
                  f"{os.path.join(str(dest), 'export.json')}", highlight=False, soft_wrap=True)
    missing = {k: v for k, v in summary["frames_without"].items() if v}
    if missing:
        err_console.print(f"frames without a mask member (key omitted in their files): {json.dumps(missing)}")
    if summary["skipped"] or summary["damaged_manifest"]:
        err_console.print(f"{len(summary['skipped'])} frame(s) skipped, {len(summary['damaged_manifest'])} "
                          "unreadable manifest file(s): the export is incomplete", highlight=False)
        raise typer.Exit(code=1)


def sensors_cmd(out: str = typer.Argument(..., help="Dataset root."),
                data_root: Path = typer.Argument(..., help="The nuPlan data root the dataset was built from.")) -> None:
    """Add sensor metadata (cameras' images and calibration, LiDAR-to-ego, per frame) to a dataset built without
    it: sensors/<log>/<scene_token>.parquet, read from the logs' DBs. A log that cannot be found or read is named
    (its scenes get none) and the exit code is 1."""
    from nuplan_occ.sensors import add_sensors

    summary = add_sensors(out, data_root)
    console.print(f"sensor metadata of {summary['frames']} frames ({summary['scenes']} scenes, {summary['rows']} camera "
                  f"rows, {summary['without_image']} without an image within 50 ms) written to {out}/sensors",
                  highlight=False, soft_wrap=True)
    for problem in summary["problems"]:
        err_console.print(problem, highlight=False, soft_wrap=True)
    if summary["problems"]:
        raise typer.Exit(code=1)


def compact_cmd(out: str = typer.Argument(..., help="Dataset root (path or fsspec URL)."),
                strict: bool = typer.Option(False, "--strict", help="Refuse to compact (exit 1) if a manifest "
                                            "file is unreadable.")) -> None:
    """Fold the manifest's fragments into one large file, dropping superseded rows (readers see the same
    rows; safe while builds run; run one compaction at a time). Unreadable manifest files are left where
    they are, never folded or deleted; they are named and the exit code is 1."""
    from nuplan_occ.storage.compact import compact

    result = compact(out, strict=strict)
    console.print(f"{out}: {result.files_before} manifest file(s), {result.rows_before:,} rows -> "
                  f"{result.output} ({result.rows_after:,} visible rows)", highlight=False, soft_wrap=True)
    if result.damaged:
        err_console.print(f"{len(result.damaged)} unreadable manifest file(s) left in place, not folded",
                          highlight=False)
        raise typer.Exit(code=1)


def report_cmd(
    out: str = typer.Argument(..., help="Dataset root."),
    report_dir: Optional[Path] = typer.Option(None, "--out", help="Report folder (default OUT/report; required "
                                               "for a dataset at a URL)."),
    every: int = typer.Option(10, "--every", min=1, help="A top-down thumbnail every N frames of a scene."),
    work_dir: Optional[Path] = typer.Option(None, help="The build's work folder holding build_log.jsonl (default "
                                            "as for build)."),
) -> None:
    """Static HTML report of a build (opens from disk): summary, flagged scenes and frames, per-scene pages."""
    from rich.progress import Progress

    from nuplan_occ.report import write_report

    if report_dir is None and "://" in out and not out.startswith("file://"):
        raise typer.BadParameter(f"{out} is a URL: give --out, a local folder for the report")
    with Progress(console=err_console, transient=True) as progress:
        task = progress.add_task("report", total=None)
        result = write_report(out, report_dir, every=every, work_root=work_dir,
                              progress=lambda done, total, scene: progress.update(
                                  task, completed=done, total=total, description=scene))
    by_rule = ", ".join(f"{name} {count}" for name, count in result.rule_frames.items() if count) or "none"
    console.print(f"{result.scenes} scenes ({result.rendered} rendered, {result.reused} unchanged), "
                  f"{result.flagged_frames} flagged frames ({by_rule})", highlight=False)
    console.print(f"report written to {result.index}", highlight=False, soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add the dataset tools to the main CLI app."""
    app.command("view")(view_cmd)
    app.command("eval")(eval_cmd)
    app.command("stats")(stats_cmd)
    app.command("validate")(validate_cmd)
    app.command("export")(export_cmd)
    app.command("sensors")(sensors_cmd)
    app.command("compact")(compact_cmd)


    app.command("report")(report_cmd)
