"""Rich tables of an `evaluate_predictions` result (the field's metrics), for `nuplan-occ eval`."""

from __future__ import annotations

from rich.table import Table


def _pct(value: float | None) -> str:
    """A ratio as a percentage to 2 decimals; '-' for None / NaN (class in neither grid)."""
    return "-" if value is None or value != value else f"{100 * value:.2f}"


def field_tables(result: dict) -> list[Table]:
    """Per-class Occ3D-style IoU and RayIoU@1/2/4 m with their means, then the F-score line."""
    occ3d, rays = result["occ3d"], result["rayiou"]
    title = (f"{result['frames_matched']} frames, mask: {result['mask']} (IoU in %; '-' = class in neither "
             f"truth nor prediction, left out of the mean)")
    table = Table(title=title)
    table.add_column("class")
    table.add_column("IoU", justify="right")
    thresholds = list(rays["miou"]) if rays else []
    for t in thresholds:
        table.add_column(f"RayIoU@{t:g}", justify="right")
    for class_id, name in result["class_names"].items():
        table.add_row(f"{name} ({class_id})", _pct(occ3d["per_class"][class_id]),
                      *(_pct(rays["per_class"][t][class_id]) for t in thresholds))
    table.add_row("[bold]mean[/bold]", f"[bold]{_pct(occ3d['miou'])}[/bold]",
                  *(f"[bold]{_pct(rays['miou'][t])}[/bold]" for t in thresholds))
    summary = Table(title="summary (%)")
    for name in ("mIoU", "geometry IoU", "RayIoU", "F-score", "precision", "recall"):
        summary.add_column(name, justify="right")
    f = result["fscore"]
    summary.add_row(_pct(occ3d["miou"]), _pct(occ3d["geometry_iou"]), _pct(rays["rayiou"]) if rays else "-",
                    _pct(f["fscore"]), _pct(f["precision"]), _pct(f["recall"]))
    summary.caption = (f"F-score: occupied voxel centres within {f['threshold_m']:g} m, mean over frames; "
                       f"RayIoU over {rays['n_rays']:,} rays" if rays else
                       f"F-score: occupied voxel centres within {f['threshold_m']:g} m, mean over frames")
    return [table, summary]
