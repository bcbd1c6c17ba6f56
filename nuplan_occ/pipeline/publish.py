"""Publishing a finished scene, done by the worker that built it (local process or Ray task): commit
the scene's manifest fragment right after its shard, then trim the scene's work folder.

Work-folder policy (`--keep-work`), applied only after the scene is published:
    all      keep every stage's cache entry;
    default  keep the entries of the stages marked `kept` (`Stage.kept`): small entries that make a param
             change cheap (poses, corrected boxes, surfaces, the manifest rows, so a rerun is answered
             without work); drop the others (point clouds, aggregates, per-frame observations), which are
             cheaper to recompute than to store;
    none     drop the scene's whole work folder.
Cache keys do not depend on the policy: a dropped entry is recomputed when a later stage needs it,
with identical bytes (stages are deterministic).
"""

from __future__ import annotations

import shutil
from collections import Counter
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nuplan_occ import __version__
from nuplan_occ.io.errors import PoseGapError
from nuplan_occ.io.reader import NuplanLog, open_log
from nuplan_occ.pipeline.scene import SceneTask, output_slots
from nuplan_occ.storage import DatasetWriter, FrameRecord

KEEP_WORK = ("all", "default", "none")


def kept_stages(pipeline: list) -> frozenset[str]:
    """Names of the stages whose cache entries the default work-folder policy keeps."""
    return frozenset(stage.name for stage in pipeline if stage.kept)


def params_metadata(params: dict[str, Any]) -> dict[str, Any]:
    """Params as plain JSON for the dataset metadata."""
    return {name: asdict(value) if is_dataclass(value) else value for name, value in params.items()}


def scene_writer(task: SceneTask) -> DatasetWriter:
    """The dataset writer of a task's output (dataset.json names the params and software)."""
    return DatasetWriter(task.out_root, metadata={"params": params_metadata(task.params),
                                                  "software": f"nuplan-occ {__version__}"})


def failed_scene_rows(task: SceneTask, reason: str) -> list[dict]:
    """Write failure rows for every output frame of a scene that could not be built at all (a frame without a
    usable logged pose gets the nearest one, or the identity when the log has none: its row says it failed)."""
    load = task.params["load"]
    log = open_log(task.db_path, task.sensor_root)
    own = log.frames_of_scene(task.scene_token)
    slots = output_slots(own, load.rate_hz, load.sweep_rate_hz)
    records = [FrameRecord(log=task.log_name, log_id=task.log_id, scene_token=task.scene_token,
                           scene_name=task.scene_name, frame_index=f.index, token=f.token,
                           timestamp_us=f.timestamp_us, ego_to_global=_stand_in_pose(log, f), arrays={},
                           columns={"output_index": slots[f.token]}, status="failed", failure_reason=reason)
               for f in own if f.token in slots]
    return DatasetWriter(task.out_root, metadata={"params": {}}).write_shard(task.shard_key, records)


def _stand_in_pose(log: NuplanLog, frame) -> np.ndarray:
    """The frame's logged pose, else the nearest usable one, else the identity (T_global_from_ego)."""
    try:
        return log.frame_pose(frame)
    except PoseGapError:
        try:
            return log.nearest_pose(frame.timestamp_us)
        except PoseGapError:
            return np.eye(4)


def publish_scene(task: SceneTask, rows: list[dict], keep_work: str, kept: frozenset[str]) -> None:
    """Commit the scene's rows (one fragment; nothing if already published), then apply the work policy
    (kept: the stages whose entries the default policy keeps)."""
    scene_writer(task).commit(rows)
    trim_work(task.work_dir, keep_work, kept)


def trim_work(work_dir: Path, keep_work: str, kept: frozenset[str]) -> None:
    """Apply a work-folder policy to one scene's stage cache folder (see module docstring)."""
    if keep_work not in KEEP_WORK:
        raise ValueError(f"keep_work {keep_work!r} is not one of {KEEP_WORK}")
    if keep_work == "none":
        shutil.rmtree(work_dir, ignore_errors=True)
    elif keep_work == "default" and work_dir.is_dir():
        for stage_dir in work_dir.iterdir():
            if stage_dir.is_dir() and stage_dir.name not in kept:
                shutil.rmtree(stage_dir, ignore_errors=True)


def _short_reason(reason: str) -> str:
    return reason.splitlines()[0][:160] if reason else "unknown"


def row_counts(rows: list[dict]) -> tuple[int, int, Counter, int]:
    """(ok frames, failed frames, failure reasons (first line), stored bytes of the ok frames)."""
    built = failed = stored = 0
    reasons: Counter = Counter()
    for row in rows:
        if row.get("status") == "ok":
            built += 1
            stored += sum(int(v) for k, v in row.items() if k.endswith("_nbytes") and v is not None)
        else:
            failed += 1
            reasons[_short_reason(row.get("failure_reason", ""))] += 1
    return built, failed, reasons, stored
