"""Finding log DBs, sensor blobs and maps under a nuPlan data root (the released layout below).

Released layout: <root>/nuplan-v1.1/splits/<split>/<log>.db, <root>/nuplan-v1.1/sensor_blobs/<log>/...,
<root>/maps/<map_name>/<version>/map.gpkg. Configs disagree on where splits live, so DBs are globbed.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from nuplan_occ.io.errors import MissingLogError


def split_folder(data_root: str | Path, split: str) -> Path | None:
    """The first existing folder of a split (splits/<split> under nuplan-v1.1 or the root, or <split>)."""
    root = Path(data_root)
    for candidate in (root / "nuplan-v1.1" / "splits" / split, root / "nuplan-v1.1" / split,
                      root / "splits" / split, root / split):
        if candidate.is_dir():
            return candidate
    return None


def resolve_logs(
    data_root: str | Path,
    split: str | None = "mini",
    log_names: Sequence[str] | None = None,
    db_paths: Sequence[str] | None = None,
) -> list[Path]:
    """Sorted DB paths to process.

    db_paths, if given, are used as they are (each must exist). Otherwise `**/*.db` is globbed under the
    split's folder when it exists, else under data_root, and filtered by log_names (DB stems; a '.db'
    suffix is allowed). MissingLogError names the missing file, names or folder.
    """
    if db_paths:
        paths = [Path(p) for p in db_paths]
        for path in paths:
            if not path.is_file():
                raise MissingLogError(path, "log database file not found")
        return sorted(paths)
    root = Path(data_root)
    base = (split_folder(root, split) if split else None) or root
    if not base.is_dir():
        raise MissingLogError(base, "data root folder not found")
    found = sorted(p for p in base.glob("**/*.db") if p.is_file())
    if log_names:
        wanted = {name[:-3] if name.endswith(".db") else name for name in log_names}
        found = [p for p in found if p.stem in wanted]
        missing = sorted(wanted - {p.stem for p in found})
        if missing:
            raise MissingLogError(base, f"no DB for log(s) {', '.join(missing)}")
    if not found:
        raise MissingLogError(base, "no *.db log files found")
    return found


def guess_sensor_root(db_path: str | Path) -> Path:
    """The sensor_blobs folder of a DB: the first `sensor_blobs` or `nuplan-v1.1/sensor_blobs` found next
    to an ancestor of the DB; if none exists, `<db>/../../../sensor_blobs` (the released layout)."""
    db_path = Path(db_path).resolve()
    for folder in db_path.parents:
        for candidate in (folder / "sensor_blobs", folder / "nuplan-v1.1" / "sensor_blobs"):
            if candidate.is_dir():
                return candidate
    parents = db_path.parents
    return parents[min(2, len(parents) - 1)] / "sensor_blobs"


def sensor_root_for(db_path: str | Path, data_root: str | Path) -> Path:
    """The sensor_blobs folder for a DB under data_root: `<data_root>/nuplan-v1.1/sensor_blobs` or
    `<data_root>/sensor_blobs` if one exists, data_root itself if it holds `<log name>/`, else the guess
    from the DB's location (guess_sensor_root)."""
    root = Path(data_root)
    for candidate in (root / "nuplan-v1.1" / "sensor_blobs", root / "sensor_blobs"):
        if candidate.is_dir():
            return candidate
    if (root / Path(db_path).stem).is_dir():
        return root
    return guess_sensor_root(db_path)


def maps_root_for(data_root: str | Path, maps_root: str | Path | None = None) -> Path:
    """The maps folder: maps_root if given, else $NUPLAN_MAPS_ROOT, else <data_root>/maps."""
    if maps_root is not None:
        return Path(maps_root)
    env = os.environ.get("NUPLAN_MAPS_ROOT")
    return Path(env) if env else Path(data_root) / "maps"
