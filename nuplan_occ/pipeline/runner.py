"""Runs the stages of a pipeline (the build's is `nuplan_occ.stages.PIPELINE`) for one scene, with every scene stage's output cached under the
work folder by a key of (stage, params, code version, input keys).

The frame stages run as one stream: for each output frame in order, every frame stage runs on it and the
last one's `record` is encoded into the scene's shard at once; the frame's grids are released before the
next frame is composed (a frame stage's `prepare` runs once, before the first frame). The stream's scene
output, `rows` (the shard's manifest rows), is cached under the last frame stage's key, so a finished scene
is answered from the cache; a scene interrupted mid-stream starts its stream again (its shard is published
only when complete), giving the same bytes."""

from __future__ import annotations

import resource
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from nuplan_occ.io.errors import NuplanFormatError
from nuplan_occ.pipeline.cache import StageCache, stable_hash
from nuplan_occ.pipeline.params import ConfigError, default_params
from nuplan_occ.pipeline.memory import release_free_memory, reuse_freed_pages
from nuplan_occ.pipeline.publish import failed_scene_rows, kept_stages, publish_scene, row_counts
from nuplan_occ.pipeline.scene import SceneTask, source_fingerprint
from nuplan_occ.recon.params import ReconError
from nuplan_occ.storage.errors import StorageWriteError

EventSink = Callable[[tuple[str, str, str]], None]
"""Receives (log name, scene name, stage name) when a stage starts; "done" as the stage when finished."""


@dataclass
class SceneResult:
    """What a worker returns for one scene, whose shard and manifest fragment it has published itself:
    frame counts, failure reasons (first line -> frames) and stored bytes of its rows; computed: stages
    that ran (the others were found in the cache); error: set when the scene failed."""

    log_name: str
    scene_name: str
    frames_built: int = 0
    frames_failed: int = 0
    failure_reasons: dict[str, int] = field(default_factory=dict)
    bytes_total: int = 0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    computed: list[str] = field(default_factory=list)
    error: str = ""
    peak_rss_mb: float = 0.0  # peak RSS of the worker process so far


def section_params(task: SceneTask, pipeline: list, stage) -> Any:
    """The params `stage` reads: its section of the task's params, else the section's declared defaults."""
    if stage.params_name in task.params:
        return task.params[stage.params_name]
    return default_params(pipeline)[stage.params_name]


def task_source_key(task: SceneTask, pipeline: list) -> str:
    """Identity of the scene's input: the fingerprint (path, size, mtime) of its DB file and of every file the
    stages reading the task declare they read (`Stage.sources`: the scene's point cloud blobs, the map),
    plus the scene token; a file put back, replaced or removed changes it."""
    files = [Path(task.db_path)]
    for stage in pipeline:
        if "task" in stage.inputs and stage.sources is not None:
            files.extend(stage.sources(task, section_params(task, pipeline, stage)))
    return stable_hash("source", source_fingerprint(files), task.scene_token, task.sensor_root, task.maps_root)


def stage_keys(task: SceneTask, pipeline: list) -> dict[str, str]:
    """Cache key of every stage, derived from keys alone (no stage has to run to know them):
    key = hash(stage name, params, code version, keys of the stages that made its inputs)."""
    artifact_keys: dict[str, str] = {"task": task_source_key(task, pipeline)}
    keys: dict[str, str] = {}
    for stage in pipeline:
        keys[stage.name] = stable_hash(stage.name, section_params(task, pipeline, stage), stage.code_version(),
                                       [artifact_keys[name] for name in stage.inputs])
        artifact_keys.update({name: keys[stage.name] for name in stage.outputs})
    return keys


def run_stages(task: SceneTask, pipeline: list, wanted: tuple[str, ...], events: EventSink | None = None,
               result: SceneResult | None = None) -> dict[str, Any]:
    """The `wanted` artifacts of the scene. Works backwards from them: a stage runs only when its
    outputs are not in the cache, so a finished scene is answered from the cache without reading input.
    An artifact is dropped from memory once every stage that reads it is done (unless it is wanted)."""
    cache = StageCache(task.work_dir)
    keys = stage_keys(task, pipeline)
    frame_stages = [stage for stage in pipeline if stage.per_frame]
    frame_artifacts = {name for stage in frame_stages for name in stage.outputs}
    producer = {name: stage for stage in pipeline if not stage.per_frame for name in stage.outputs}
    if frame_stages:
        producer[STREAM_OUTPUT] = frame_stages[-1]
    artifacts: dict[str, Any] = {"task": task}
    group = {stage.name: (frame_stages[-1].name if stage.per_frame else stage.name) for stage in pipeline}
    readers: dict[str, set[str]] = {}
    for stage in pipeline:
        for name in stage.inputs:
            readers.setdefault(name, set()).add(group[stage.name])
    done: set[str] = set()

    def finished(stage) -> None:
        done.add(stage.name)
        for name in {n for s in pipeline if group[s.name] == stage.name for n in s.inputs}:
            if name not in wanted and readers[name] <= done:
                artifacts.pop(name, None)
        release_free_memory()

    def obtain(name: str) -> Any:
        if name not in artifacts:
            stage = producer[name]
            artifacts.update(run_or_reuse(stage))
        return artifacts[name]

    def params_of(stage) -> Any:
        return section_params(task, pipeline, stage)

    def timed(stage, seconds: float) -> None:
        if result is not None:
            result.stage_seconds[stage.name] = result.stage_seconds.get(stage.name, 0.0) + seconds

    def run_or_reuse(stage) -> dict[str, Any]:
        outputs = cache.get(stage.name, keys[stage.name]) if stage.cache else None
        if outputs is not None and _outputs_still_valid(stage.name, outputs, task):
            finished(stage)
            return outputs
        if stage.per_frame:
            outputs = {STREAM_OUTPUT: stream_frames()}
            if stage.cache:
                cache.put(stage.name, keys[stage.name], outputs)
        else:
            inputs = {name: obtain(name) for name in stage.inputs}
            if events:
                events((task.log_name, task.scene_name, stage.name))
            started = time.perf_counter()
            outputs = stage.run(inputs, params_of(stage))
            if stage.cache:  # item outputs may be one-pass iterables made while the cache stores them
                outputs.update(cache.put(stage.name, keys[stage.name], outputs, stage.item_outputs))
            timed(stage, time.perf_counter() - started)
            del inputs
        if result is not None and stage.cache:
            result.computed.append(stage.name)
        finished(stage)
        return outputs

    def stream_frames() -> list[dict]:
        from nuplan_occ.storage import DatasetWriter

        scene_inputs = {name for stage in frame_stages for name in stage.inputs if name not in frame_artifacts}
        for name in sorted(scene_inputs, key=lambda n: pipeline.index(producer[n]) if n in producer else -1):
            obtain(name)  # in pipeline order, so an artifact only earlier stages read is dropped early
        inputs = [{name: obtain(name) for name in stage.inputs if name not in frame_artifacts} for stage in frame_stages]
        for k, stage in enumerate(frame_stages):
            if stage.prepare is not None:
                started = time.perf_counter()
                inputs[k].update(stage.prepare(inputs[k], params_of(stage)))
                timed(stage, time.perf_counter() - started)
        shard = DatasetWriter(task.out_root, metadata={"params": {}}).open_shard(task.shard_key)
        for position in obtain("scene").output_positions():
            frame: dict[str, Any] = {"position": position}
            for k, stage in enumerate(frame_stages):
                if frame.get("failure") and k < len(frame_stages) - 1:
                    continue
                if events:
                    events((task.log_name, task.scene_name, stage.name))
                started = time.perf_counter()
                try:
                    frame.update(stage.run(inputs[k], frame, params_of(stage)))
                except Exception as exc:  # a frame failure is recorded in its row, never fatal to the scene
                    if k == len(frame_stages) - 1:
                        raise
                    frame["failure"] = f"{stage.name}: {type(exc).__name__}: {exc}"
                    if not isinstance(exc, EXPECTED_FAILURES):  # expected ones are told by their row
                        report_failure(f"{task.log_name}/{task.scene_name} frame {position}", exc)
                timed(stage, time.perf_counter() - started)
            shard.add(frame["record"])
        return shard.publish()

    return {name: obtain(name) for name in wanted}


EXPECTED_FAILURES = (NuplanFormatError, ConfigError, ReconError)
"""Failures of bad input or params, told in one line (unexpected ones print their traceback: a bug)."""


def report_failure(what: str, exc: Exception) -> None:
    """One line on stderr naming what failed and why for an expected failure, else the traceback."""
    if isinstance(exc, EXPECTED_FAILURES):
        print(f"nuplan-occ: {what} failed: {' '.join(str(exc).split())}", file=sys.stderr, flush=True)
    else:
        traceback.print_exc()


STREAM_OUTPUT = "rows"
"""The scene artifact of the frame stream: the manifest rows of the scene's published shard."""


def _outputs_still_valid(stage_name: str, outputs: dict[str, Any], task: SceneTask) -> bool:
    """A cached write is only valid while its shard is still published."""
    if stage_name != "write":
        return True
    from nuplan_occ.storage import shard_exists

    return shard_exists(task.out_root, task.shard_key)


def run_scene(task: SceneTask, pipeline: list, events: EventSink | None = None) -> SceneResult:
    """Build one scene with the stages of `pipeline` (execution order) and publish it (shard, manifest
    fragment, work policy: `publish.py`); never raises for a bad scene: its frames are published as failed
    and the error comes back in the result."""
    reuse_freed_pages()
    result = SceneResult(task.log_name, task.scene_name)
    try:
        rows = run_stages(task, pipeline, ("rows",), events, result)["rows"]
    except StorageWriteError:  # the output cannot be written (disk full, quota): the build stops, one line
        raise
    except Exception as exc:  # a scene failure is recorded, never fatal to the build
        result.error = f"{type(exc).__name__}: {exc}"
        report_failure(f"{task.log_name}/{task.scene_name}", exc)
        rows = failed_scene_rows(task, result.error)
    publish_scene(task, rows, task.keep_work, kept_stages(pipeline))
    result.frames_built, result.frames_failed, reasons, result.bytes_total = row_counts(rows)
    result.failure_reasons = dict(reasons)
    result.peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    if events:
        events((task.log_name, task.scene_name, "done"))
    return result
