"""The runner's two granularities on a toy DAG: scene stages run once and are cached; frame stages run
frame by frame, each frame's arrays are released before the next frame is composed, a frame stage's
exception becomes that frame's failed row, and the streamed shard has the bytes `write_shard` gives."""

from __future__ import annotations

import gc
import weakref
from dataclasses import dataclass, field

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.pipeline.runner import SceneResult, run_stages
from nuplan_occ.pipeline.scene import SceneTask
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.storage import DatasetWriter, FrameRecord

GRID = DEFAULT_GRID
FRAMES = 5
BROKEN = 3  # position whose voxelize raises


@dataclass(frozen=True)
class _Params:
    level: int = 1


@dataclass
class _Scene:
    task: SceneTask
    calls: list = field(default_factory=list)
    alive: list = field(default_factory=list)  # weak references to every frame's grid

    def output_positions(self) -> list[int]:
        return list(range(FRAMES))


def _load(inputs, params):
    return {"scene": _Scene(inputs["task"])}


def _voxelize(inputs, frame, params):
    scene = inputs["scene"]
    position = frame["position"]
    gc.collect()
    scene.calls.append(("voxelize", position, sum(ref() is not None for ref in scene.alive)))
    if position == BROKEN:
        raise ValueError("no surface near the frame")
    grid = np.full(GRID.shape, position + params.level, dtype=np.uint8)
    scene.alive.append(weakref.ref(grid))
    return {"grid": grid}


def _record(task, position, **fields) -> FrameRecord:
    return FrameRecord(log=task.log_name, log_id=task.log_id, scene_token=task.scene_token, scene_name=task.scene_name,
                       frame_index=position, token=f"t{position}", timestamp_us=position, ego_to_global=np.eye(4),
                       **fields)


def _write(inputs, frame, params):
    task, position = inputs["scene"].task, frame["position"]
    if frame.get("failure"):
        return {"record": _record(task, position, status="failed", failure_reason=frame["failure"])}
    return {"record": _record(task, position, arrays={"semantics": frame["grid"]})}


PIPELINE = [
    Stage("load", ("task",), ("scene",), _Params, _load, cache=False),
    Stage("voxelize", ("scene",), ("grid",), _Params, _voxelize, per_frame=True),
    Stage("write", ("scene", "grid"), ("record",), _Params, _write, per_frame=True),
]


def test_frames_stream_one_at_a_time_and_a_failing_frame_gets_its_row(tmp_path):
    task = SceneTask("db", "sensors", "maps", "log-a", 1, "scene-token", "scene-a", str(tmp_path / "out"),
                     str(tmp_path / "work"), {})
    result = SceneResult("log-a", "scene-a")
    events = []
    artifacts = run_stages(task, PIPELINE, ("rows", "scene"), lambda event: events.append(event[2]), result)
    rows, calls = artifacts["rows"], artifacts["scene"].calls
    assert [c[1] for c in calls] == list(range(FRAMES))
    assert all(alive == 0 for _, _, alive in calls)  # no earlier frame's grid is alive when the next is composed
    assert [r["status"] for r in rows] == ["ok", "ok", "ok", "failed", "ok"]
    assert rows[BROKEN]["failure_reason"] == "voxelize: ValueError: no surface near the frame"
    assert events.count("voxelize") == FRAMES and events.count("write") == FRAMES
    assert set(result.stage_seconds) == {"load", "voxelize", "write"}

    expected = [_record(task, p, arrays={"semantics": np.full(GRID.shape, p + 1, dtype=np.uint8)}) for p in range(FRAMES)]
    expected[BROKEN] = _record(task, BROKEN, status="failed", failure_reason=rows[BROKEN]["failure_reason"])
    streamed = (tmp_path / "out" / "shards" / "log-a" / "scene-a.tar").read_bytes()
    reference = tmp_path / "reference"
    DatasetWriter(str(reference), {"params": {}}).write_shard(task.shard_key, expected[::-1])
    assert (reference / "shards" / "log-a" / "scene-a.tar").read_bytes() == streamed

    again = SceneResult("log-a", "scene-a")
    assert run_stages(task, PIPELINE, ("rows",), None, again)["rows"] == rows
    assert again.computed == []  # the stream's rows come from the cache while the shard is published


def _prepare(inputs, params):
    inputs["scene"].calls.append(("prepare", None, 0))
    return {"base": 1}


def _voxelize_prepared(inputs, frame, params):
    return {"grid": np.full(GRID.shape, inputs["base"] + frame["position"], dtype=np.uint8)}


def test_a_frame_stage_prepares_once_per_scene_before_its_first_frame(tmp_path):
    task = SceneTask("db", "sensors", "maps", "log-a", 1, "scene-token", "scene-a", str(tmp_path / "out"),
                     str(tmp_path / "work"), {})
    pipeline = [PIPELINE[0], Stage("voxelize", ("scene",), ("grid",), _Params, _voxelize_prepared, per_frame=True,
                                   prepare=_prepare), PIPELINE[2]]
    result = SceneResult("log-a", "scene-a")
    artifacts = run_stages(task, pipeline, ("rows", "scene"), None, result)
    assert artifacts["scene"].calls == [("prepare", None, 0)]
    assert [r["status"] for r in artifacts["rows"]] == ["ok"] * FRAMES
    assert "voxelize" in result.stage_seconds
    shard = (tmp_path / "out" / "shards" / "log-a" / "scene-a.tar").read_bytes()
    reference = tmp_path / "reference"
    expected = [_record(task, p, arrays={"semantics": np.full(GRID.shape, 1 + p, dtype=np.uint8)})
                for p in range(FRAMES)]
    DatasetWriter(str(reference), {"params": {}}).write_shard(task.shard_key, expected)
    assert (reference / "shards" / "log-a" / "scene-a.tar").read_bytes() == shard


def _aggregate(inputs, params):
    points = np.zeros((1000, 3))
    inputs["scene"].alive.append(weakref.ref(points))
    return {"points": points}


def _support(inputs, params):
    inputs["scene"].calls.append(("support", None, len(inputs["points"])))
    return {"support": 1}


def _map(inputs, params):
    gc.collect()
    inputs["scene"].calls.append(("map", None, sum(ref() is not None for ref in inputs["scene"].alive)))
    return {"layers": 2}


def _voxelize_from(inputs, frame, params):
    return {"grid": np.full(GRID.shape, inputs["layers"] + inputs["support"], dtype=np.uint8)}


def test_scene_stages_run_in_pipeline_order_and_release_what_only_earlier_stages_read(tmp_path):
    """The frame stages ask for `layers` before `support`, yet support runs first (pipeline order), and the
    points only support reads are released before the map stage runs."""
    task = SceneTask("db", "sensors", "maps", "log-a", 1, "scene-token", "scene-a", str(tmp_path / "out"),
                     str(tmp_path / "work"), {})
    pipeline = [PIPELINE[0],
                Stage("aggregate", ("scene",), ("points",), _Params, _aggregate, cache=False),
                Stage("support", ("scene", "points"), ("support",), _Params, _support, cache=False),
                Stage("map", ("scene",), ("layers",), _Params, _map, cache=False),
                Stage("voxelize", ("scene", "layers", "support"), ("grid",), _Params, _voxelize_from, per_frame=True),
                PIPELINE[2]]
    artifacts = run_stages(task, pipeline, ("rows", "scene"))
    assert artifacts["scene"].calls == [("support", None, 1000), ("map", None, 0)]
    assert [r["status"] for r in artifacts["rows"]] == ["ok"] * FRAMES
