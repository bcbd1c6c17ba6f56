"""Per-log summary (counts of scenes, frames, boxes, points per LiDAR) for `inspect`-style reports."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rich.table import Table

from nuplan_occ.io.errors import MissingBlobError, NuplanFormatError
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.io.types import LIDAR_NAMES, NUPLAN_CATEGORIES

UNKNOWN_LIDAR = "unknown"


def summarize_log(db_path: str | Path, sensor_root: str | Path | None = None) -> dict:
    """Summary of one log; reads every PCD of the log.

    Keys: log, location, map, scenes, frames, duration_s (first to last lidar_pc), boxes (category -> count),
    points (LiDAR name of LIDAR_NAMES or "unknown" -> total points over all frames), blobs_read,
    missing_blobs, failures (messages of format errors, each naming its file). A log that cannot be opened
    gives a row with only log and failures filled.
    """
    row: dict = {"log": Path(db_path).stem, "location": "", "map": "", "scenes": 0, "frames": 0, "duration_s": 0.0,
                 "boxes": dict.fromkeys(NUPLAN_CATEGORIES, 0), "points": {}, "blobs_read": 0, "missing_blobs": 0,
                 "failures": []}
    try:
        log = NuplanLog(db_path, sensor_root)
    except NuplanFormatError as exc:
        row["failures"].append(str(exc))
        return row
    with log:
        frames = log.frames
        row.update(log=log.meta.logfile, location=log.meta.location, map=log.meta.map_name,
                   scenes=len(log.scenes), frames=len(frames),
                   duration_s=(frames[-1].timestamp_us - frames[0].timestamp_us) / 1e6 if frames else 0.0)
        try:
            row["boxes"] = log.box_counts()
        except NuplanFormatError as exc:
            row["failures"].append(str(exc))
        counts = np.zeros(len(LIDAR_NAMES) + 1, dtype=np.int64)  # last slot: unknown lidar_info (-1)
        for frame in frames:
            try:
                cloud = log.load_points(frame)
            except MissingBlobError:
                row["missing_blobs"] += 1
                continue
            except NuplanFormatError as exc:
                row["failures"].append(str(exc))
                continue
            row["blobs_read"] += 1
            counts += np.bincount(np.where(cloud.lidar_info < 0, len(LIDAR_NAMES), cloud.lidar_info),
                                  minlength=len(counts))
        names = [LIDAR_NAMES[i] for i in range(len(LIDAR_NAMES))] + [UNKNOWN_LIDAR]
        row["points"] = {name: int(n) for name, n in zip(names, counts) if n}
    return row


def render_summary(rows: Sequence[dict]) -> Table:
    """A rich table with one line per summarize_log row."""
    table = Table(title="nuPlan logs")
    for column in ("log", "location", "scenes", "frames", "duration s", "boxes", "points", "missing blobs",
                   "failures"):
        table.add_column(column, justify="right" if column not in ("log", "location", "boxes", "points") else "left")
    for row in rows:
        boxes = ", ".join(f"{k}:{v}" for k, v in row["boxes"].items() if v) or "-"
        points = ", ".join(f"{k}:{v}" for k, v in row["points"].items()) or "-"
        table.add_row(row["log"], row["location"], str(row["scenes"]), str(row["frames"]),
                      f"{row['duration_s']:.1f}", boxes, points, str(row["missing_blobs"]), str(len(row["failures"])))
    return table
