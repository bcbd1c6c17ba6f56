"""`nuplan-occ build`: plan scene tasks over the selected logs, run them on an executor, commit the
manifest as scenes finish, and summarise (frames built, failures with reasons, time per stage, bytes).

The manifest is committed after every finished scene (at most every `commit_every_s` seconds, and at
the end), so an interrupted build keeps what it published; a rerun reuses every cached stage output.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Callable

from nuplan_occ import __version__
from nuplan_occ.io.data_root import maps_root_for, resolve_logs, sensor_root_for
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.pipeline.executors import execute
from nuplan_occ.pipeline.runner import SceneResult
from nuplan_occ.pipeline.scene import SceneTask, log_id_of, output_slots
from nuplan_occ.storage import DatasetWriter, FrameRecord


@dataclass
class BuildSummary:
    """Totals of one build run."""

    frames_built: int = 0
    frames_failed: int = 0
    failure_reasons: Counter = field(default_factory=Counter)
    scenes: int = 0
    scenes_failed: int = 0
    scenes_fully_cached: int = 0
    stage_seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    bytes_total: int = 0
    wall_seconds: float = 0.0
    peak_rss_mb: float = 0.0

    @property
    def bytes_per_frame(self) -> float:
        return self.bytes_total / self.frames_built if self.frames_built else 0.0

    def add(self, result: SceneResult) -> None:
        """Fold one scene's result in."""
        self.scenes += 1
        self.scenes_failed += bool(result.error)
        self.scenes_fully_cached += not result.error and not result.computed
        self.peak_rss_mb = max(self.peak_rss_mb, result.peak_rss_mb)
        for stage, seconds in result.stage_seconds.items():
            self.stage_seconds[stage] += seconds
        for row in result.rows:
            if row.get("status") == "ok":
                self.frames_built += 1
                self.bytes_total += sum(int(v) for k, v in row.items() if k.endswith("_nbytes") and v is not None)
            else:
                self.frames_failed += 1
                self.failure_reasons[_short_reason(row.get("failure_reason", ""))] += 1

    def to_dict(self) -> dict[str, Any]:
        return {
            "frames_built": self.frames_built, "frames_failed": self.frames_failed,
            "failure_reasons": dict(self.failure_reasons), "scenes": self.scenes,
            "scenes_failed": self.scenes_failed, "scenes_fully_cached": self.scenes_fully_cached,
            "stage_seconds": dict(self.stage_seconds), "bytes_per_frame": self.bytes_per_frame,
            "wall_seconds": self.wall_seconds, "peak_rss_mb_per_worker": self.peak_rss_mb,
        }


def _short_reason(reason: str) -> str:
    return reason.splitlines()[0][:160] if reason else "unknown"


def default_work_root(out: str) -> Path:
    """Stage outputs live under OUT/work for a local OUT, else in a local cache folder keyed by OUT."""
    if "://" not in out or out.startswith("file://"):
        return Path(out.removeprefix("file://")) / "work"
    digest = hashlib.sha256(out.encode()).hexdigest()[:16]
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nuplan-occ" / "work" / digest


def plan_tasks(db_paths: list[Path], data_root: Path, maps_root: Path, out: str, work_root: Path,
               params: dict[str, Any]) -> list[SceneTask]:
    """One task per scene with at least one sweep, in log then scene-name order."""
    tasks = []
    for db_path in db_paths:
        sensor_root = sensor_root_for(db_path, data_root)
        with NuplanLog(db_path, sensor_root) as log:
            log_name = log.meta.logfile or db_path.stem
            for scene in log.scenes:
                if log.frames_of_scene(scene.token):
                    tasks.append(SceneTask(str(db_path), str(sensor_root), str(maps_root), log_name,
                                           log_id_of(log_name), scene.token, scene.name, out, str(work_root), params))
    return tasks


def failed_scene_rows(task: SceneTask, reason: str, rate_hz: float, sweep_rate_hz: float) -> list[dict]:
    """Publish failure rows for every output frame of a scene that could not be built at all."""
    with NuplanLog(task.db_path, task.sensor_root) as log:
        own = log.frames_of_scene(task.scene_token)
        slots = output_slots(own, rate_hz, sweep_rate_hz)
        records = [FrameRecord(log=task.log_name, log_id=task.log_id, scene_token=task.scene_token,
                               scene_name=task.scene_name, frame_index=f.index, token=f.token,
                               timestamp_us=f.timestamp_us, ego_to_global=log.frame_pose(f), arrays={},
                               columns={"output_index": slots[f.token]}, status="failed", failure_reason=reason)
                   for f in own if f.token in slots]
    return DatasetWriter(task.out_root, metadata={"params": {}}).write_shard(task.shard_key, records)


def params_metadata(params: dict[str, Any]) -> dict[str, Any]:
    """Params as plain JSON for the dataset metadata."""
    return {name: asdict(value) if is_dataclass(value) else value for name, value in params.items()}


def run_build(data_root: Path, out: str, params: dict[str, Any], *, split: str | None = "mini",
              log_names: list[str] | None = None, db_paths: list[str] | None = None, maps_root: str | None = None,
              workers: int = 1, executor: str = "local", ray_address: str | None = None,
              work_root: Path | None = None,
              on_plan: Callable[[list[SceneTask]], None] | None = None,
              on_event: Callable[[tuple[str, str, str]], None] | None = None,
              commit_every_s: float = 10.0) -> BuildSummary:
    """Build the dataset at `out` from the logs under `data_root`; returns the summary. work_root: where
    stage outputs are cached (default: see `default_work_root`)."""
    started = time.perf_counter()
    logs = resolve_logs(data_root, split=split, log_names=log_names, db_paths=db_paths)
    maps = maps_root_for(data_root, maps_root)
    tasks = plan_tasks(logs, Path(data_root), maps, out, Path(work_root) if work_root else default_work_root(out), params)
    if on_plan:
        on_plan(tasks)
    writer = DatasetWriter(out, metadata={"params": params_metadata(params), "software": f"nuplan-occ {__version__}"})
    summary = BuildSummary()
    pending_rows: list[dict] = []
    last_commit = time.monotonic()
    by_scene = {(t.log_name, t.scene_name): t for t in tasks}
    for result in execute(tasks, executor, workers, ray_address, on_event or (lambda event: None)):
        if result.error:
            result.rows = failed_scene_rows(by_scene[(result.log_name, result.scene_name)], result.error,
                                            params["load"].rate_hz, params["load"].sweep_rate_hz)
        summary.add(result)
        pending_rows.extend(result.rows)
        if time.monotonic() - last_commit >= commit_every_s:
            writer.commit(pending_rows)
            pending_rows, last_commit = [], time.monotonic()
    writer.commit(pending_rows)
    summary.wall_seconds = time.perf_counter() - started
    return summary
