"""`nuplan-occ build`: plan scene tasks over the selected logs (optionally one shard of them), run them
on an executor, and summarise (frames built, failures with reasons, time per stage, bytes).

Every worker publishes its own scenes (shard, then manifest fragment: `pipeline.publish`), so an
interrupted build keeps every finished scene, a rerun reuses every cached stage output, and any number
of build processes (disjoint or overlapping logs, any machines) may write into one output at once.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from nuplan_occ.io.data_root import maps_root_for, resolve_logs, sensor_root_for
from nuplan_occ.io.maps import usable_map
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.pipeline.build_log import BuildLog
from nuplan_occ.pipeline.executors import execute
from nuplan_occ.pipeline.params import check_params
from nuplan_occ.pipeline.runner import SceneResult
from nuplan_occ.pipeline.scene import SceneTask, log_id_of
from nuplan_occ.sensors import add_sensors


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
    sensor_problems: list[str] = field(default_factory=list)
    """One line per built log whose sensor metadata could not be written (nuplan_occ.sensors.add_sensors)."""

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
        self.frames_built += result.frames_built
        self.frames_failed += result.frames_failed
        self.bytes_total += result.bytes_total
        self.failure_reasons.update(result.failure_reasons)

    def to_dict(self) -> dict[str, Any]:
        return {
            "frames_built": self.frames_built, "frames_failed": self.frames_failed,
            "failure_reasons": dict(self.failure_reasons), "scenes": self.scenes,
            "scenes_failed": self.scenes_failed, "scenes_fully_cached": self.scenes_fully_cached,
            "stage_seconds": dict(self.stage_seconds), "bytes_per_frame": self.bytes_per_frame,
            "wall_seconds": self.wall_seconds, "peak_rss_mb_per_worker": self.peak_rss_mb,
            "sensor_problems": list(self.sensor_problems),
        }


def default_work_root(out: str) -> Path:
    """Stage outputs live under OUT/work for a local OUT, else in a local cache folder keyed by OUT."""
    if "://" not in out or out.startswith("file://"):
        return Path(out.removeprefix("file://")) / "work"
    digest = hashlib.sha256(out.encode()).hexdigest()[:16]
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nuplan-occ" / "work" / digest


def logs_of_shard(db_paths: list[Path], num_shards: int, shard_index: int) -> list[Path]:
    """The logs of build shard `shard_index` of `num_shards`: those whose DB file stem hashes to it
    (`log_id_of(stem) % num_shards`), so every machine computes the same partition from names alone."""
    if num_shards < 1 or not 0 <= shard_index < num_shards:
        raise ValueError(f"--shard-index {shard_index} must be in [0, --num-shards {num_shards})")
    return [p for p in db_paths if log_id_of(Path(p).stem) % num_shards == shard_index]


def plan_tasks(db_paths: list[Path], data_root: Path, maps_root: Path, out: str, work_root: Path,
               params: dict[str, Any], keep_work: str = "default") -> list[SceneTask]:
    """One task per scene with at least one sweep, in log then scene-name order. Warns once per log (logger
    `nuplan_occ.build`, shown on the console) when the log has no usable map or rows were dropped on reading."""
    tasks = []
    for db_path in db_paths:
        sensor_root = sensor_root_for(db_path, data_root)
        with NuplanLog(db_path, sensor_root) as log:
            log_name = log.meta.logfile or db_path.stem
            for note in [*log.notes, usable_map(maps_root, log.meta.map_name)[1]]:
                if note:
                    logging.getLogger("nuplan_occ.build").warning("warning: %s: %s", log_name, note)
            for scene in log.scenes:
                if log.frames_of_scene(scene.token):
                    tasks.append(SceneTask(str(db_path), str(sensor_root), str(maps_root), log_name,
                                           log_id_of(log_name), scene.token, scene.name, out, str(work_root), params,
                                           keep_work))
    return tasks


def run_build(data_root: Path, out: str, params: dict[str, Any], *, pipeline: list, split: str | None = "mini",
              log_names: list[str] | None = None, db_paths: list[str] | None = None, maps_root: str | None = None,
              workers: int = 1, executor: str = "local", ray_address: str | None = None,
              work_root: Path | None = None, num_shards: int = 1, shard_index: int = 0,
              keep_work: str = "default",
              on_plan: Callable[[list[SceneTask]], None] | None = None,
              on_event: Callable[[tuple[str, str, str]], None] | None = None) -> BuildSummary:
    """Build the dataset at `out` from the logs under `data_root` (shard `shard_index` of `num_shards`
    of them) with the stages of `pipeline` (`nuplan_occ.stages.PIPELINE`); returns the summary. work_root: where stage outputs are cached (default: see
    `default_work_root`); keep_work: work-folder policy (see `pipeline.publish`); each run appends its
    scenes' stage times to the build log there (`nuplan_occ.pipeline.build_log`)."""
    started = time.perf_counter()
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    for section, value in params.items():
        check_params(value, section)
    logs = logs_of_shard(resolve_logs(data_root, split=split, log_names=log_names, db_paths=db_paths),
                         num_shards, shard_index)
    maps = maps_root_for(data_root, maps_root)
    work_root = Path(work_root) if work_root else default_work_root(out)
    tasks = plan_tasks(logs, Path(data_root), maps, out, work_root, params, keep_work)
    if on_plan:
        on_plan(tasks)
    summary = BuildSummary()
    build_log = BuildLog(work_root)
    by_scene = {(t.log_name, t.scene_name): t for t in tasks}
    for result in execute(tasks, pipeline, executor, workers, ray_address, on_event or (lambda event: None)):
        summary.add(result)
        build_log.scene(by_scene[(result.log_name, result.scene_name)].scene_token, result)
    # per-scene sensor sidecars of the logs built (cameras, images, LiDAR-to-ego; storage.sensors)
    summary.sensor_problems = add_sensors(out, data_root, logs=sorted({t.log_name for t in tasks}))["problems"]
    summary.wall_seconds = time.perf_counter() - started
    return summary
