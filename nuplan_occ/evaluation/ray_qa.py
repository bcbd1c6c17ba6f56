"""`nuplan-occ qa`: ray consistency (`nuplan_occ.rays.consistency`) of every ok frame of a built dataset,
scored against a LiDAR sweep of its log, written beside the dataset without touching what is published.

Which sweep: the one the build's write stage scores each frame against (`nuplan_occ.rays.frame_qa`: the sweep
between output frames nearest in time), so the figures are the build's own qa_ray_* columns recomputed. Each
row says which sweep it used and whether that sweep's points went into the background the grid was built
from (`qa_ray_sweep_in_background`: the filter stage takes the background from every output sweep and every
n-th sweep in phase with them, so with the defaults the sweeps between frames of a scene of at least 40
sweeps are held out of the background; their object points are aggregated all the same).

Poses: the build's refined poses (its `register` stage's cache entry, kept by the default work policy) when the
work folder still holds an entry whose poses are the build's (checked against the manifest's poses, so a code
edit or a moved data root since the build does not lose them), else the log's poses (`qa_ray_poses`: refined |
logged).

Output: one Parquet file per scene, OUT/qa/ray_consistency/<log>/<scene>.parquet, written whole (atomic), a row
per ok frame keyed by `token` (with log, scene_name, scene_token, frame_index and the manifest row's
commit_id, so a rebuilt scene's stale QA is recognised and recomputed). DuckDB reads them as one table:
    SELECT * FROM read_parquet('OUT/qa/ray_consistency/**/*.parquet')
A frame that cannot be scored (its sweep failed to load, none near enough) has a row with `qa_ray_problem`
and null figures. `qa_ray_flags` names the flag rules a frame breaks (`rays.consistency.FLAG_RULES`); a scene is
flagged when more than SCENE_RULE_SHARE of its scored frames are.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.pipeline.cache import StageCache
from nuplan_occ.pipeline.scene import SceneData, SceneTask
from nuplan_occ.rays.frame_qa import FIGURES, MAX_RAYS, frame_flags, frame_ray_columns
from nuplan_occ.storage.fsio import arrow_filesystem, atomic_put, resolve
from nuplan_occ.storage.manifest import to_parquet_bytes

QA_FOLDER = "qa/ray_consistency"
"""Where the sidecar files go, under the dataset root."""

SCENE_RULE_SHARE = 0.2
"""A scene is flagged when more than this share of its scored frames is flagged."""

SCHEMA = pa.schema([
    ("token", pa.string()), ("log", pa.string()), ("scene_name", pa.string()), ("scene_token", pa.string()),
    ("frame_index", pa.int64()), ("commit_id", pa.string()), ("qa_ray_sweep_token", pa.string()),
    ("qa_ray_sweep_dt_s", pa.float64()), ("qa_ray_sweep_in_background", pa.bool_()), ("qa_ray_poses", pa.string()),
    ("qa_ray_returns", pa.int64()), ("qa_ray_scored", pa.int64()), *((name, pa.float64()) for name in FIGURES),
    ("qa_ray_flags", pa.string()), ("qa_ray_problem", pa.string()),
])
"""Columns of a sidecar file."""


POSE_MATCH_M = 1e-6
"""A cached registration is this build's when its relative poses of the output frames match the manifest's
within this (m, and radians for the rotation entries)."""


def matches_manifest(poses: np.ndarray, positions: list[int], manifest_poses: list[np.ndarray]) -> bool:
    """Whether `poses` (F, 4, 4) at `positions` move the frames relative to the first of them as the manifest's
    poses do (the manifest's are the refined poses left-multiplied by the scene's map alignment, so relative
    poses are equal)."""
    if not positions:
        return False
    relative = np.linalg.solve(poses[positions[0]][None], poses[positions])
    published = np.linalg.solve(manifest_poses[0][None], np.stack(manifest_poses))
    return bool(np.max(np.abs(relative - published)) <= POSE_MATCH_M)


def scene_poses(task: SceneTask, pipeline: list, scene: SceneData, manifest_poses: dict[str, np.ndarray]
                ) -> tuple[np.ndarray, str]:
    """(poses (F, 4, 4) T_global_from_ego in scene sweep order, "refined" | "logged"): the registration of
    the register stage's cache entries (the one keyed by these inputs, params and code first, then any other
    in the scene's folder) whose poses match the manifest's (`matches_manifest`; manifest_poses: token ->
    ego_to_global of the scene's ok frames), else the logged poses."""
    from nuplan_occ.pipeline.runner import stage_keys

    logged = np.stack([sweep.logged_pose for sweep in scene.sweeps])
    register = next((stage for stage in pipeline if "registration" in stage.outputs), None)
    if register is None:
        return logged, "logged"
    positions = [i for i, sweep in enumerate(scene.sweeps) if sweep.token in manifest_poses]
    published = [manifest_poses[scene.sweeps[i].token] for i in positions]
    cache, key = StageCache(task.work_dir), stage_keys(task, pipeline)[register.name]
    others = sorted(path.name.removesuffix(".pkl.zst") for path in (task.work_dir / register.name).glob("*.pkl.zst"))
    for candidate in [key, *(k for k in others if k != key)]:
        entry = cache.get(register.name, candidate)
        poses = None if entry is None else getattr(entry.get("registration"), "poses", None)
        if poses is not None and np.shape(poses) == logged.shape and \
                matches_manifest(np.asarray(poses, dtype=np.float64), positions, published):
            return np.asarray(poses, dtype=np.float64), "refined"
    return logged, "logged"


def background_sweeps(task: SceneTask, pipeline: list, scene: SceneData) -> set[int] | None:
    """Positions of the sweeps whose background went into the grids (the stage making `background_positions`
    decides, from its sweep_stride and stride_min_sweeps), None when the pipeline has no such stage."""
    from nuplan_occ.pipeline.runner import section_params

    stage = next((stage for stage in pipeline if "background_positions" in stage.outputs), None)
    if stage is None:
        return None
    params = section_params(task, pipeline, stage)
    return set(scene.background_positions(params.sweep_stride, params.stride_min_sweeps))


IDENTITY = ("log", "scene_name", "scene_token", "frame_index", "commit_id")
"""Manifest columns copied into each sidecar row (with `token`)."""


def scene_frames(ds) -> dict[tuple[str, str], dict[str, dict]]:
    """The ok frames of an open dataset by scene: (log, scene_token) -> token -> its IDENTITY columns and its
    manifest pose `ego_to_global` (4, 4)."""
    table = ds.columns(["token", *IDENTITY, "ego_to_global"]).to_pylist()
    out: dict[tuple[str, str], dict[str, dict]] = {}
    for row in table:
        pose = np.asarray(row.pop("ego_to_global"), dtype=np.float64).reshape(4, 4)
        out.setdefault((row["log"], row["scene_token"]), {})[row.pop("token")] = {**row, "ego_to_global": pose}
    return out


def score_scene(task: SceneTask, pipeline: list, frames: dict[str, dict], semantics: Callable[[str], np.ndarray],
                max_rays: int | None = MAX_RAYS, grid: GridSpec = DEFAULT_GRID, built: bool = True) -> list[dict]:
    """Sidecar rows of one scene: frames is the scene's entry of `scene_frames`; semantics(token) reads a grid of
    `grid`; built: the dataset is a build of this pipeline (else, e.g. an imported release, which sweeps went into
    its grids is unknown). Loads the scene through the pipeline (`run_stages`; its first stage reads the sweeps)."""
    from nuplan_occ.pipeline.runner import run_stages

    scene = run_stages(task, pipeline, ("scene",))["scene"]
    poses, pose_source = scene_poses(task, pipeline, scene, {t: f["ego_to_global"] for t, f in frames.items()})
    background = background_sweeps(task, pipeline, scene) if built else None
    return [{**dict.fromkeys(SCHEMA.names), "token": sweep.token,
             **{key: frames[sweep.token][key] for key in IDENTITY}, "qa_ray_poses": pose_source,
             **frame_ray_columns(scene, position, poses, semantics(sweep.token), background, max_rays, grid)}
            for position, sweep in enumerate(scene.sweeps) if sweep.token in frames]


@dataclass
class QaResult:
    """What `qa_dataset` did: rows (every sidecar row of the dataset's scenes), scenes scored now and reused
    (their file matched the published rows), and the scenes flagged (log/scene -> share of flagged frames)."""

    rows: list[dict] = field(default_factory=list)
    scored: int = 0
    reused: int = 0
    flagged_scenes: dict[str, float] = field(default_factory=dict)


def _sidecar_path(root: str, log: str, scene_name: str) -> str:
    return f"{root}/{QA_FOLDER}/{log}/{scene_name}.parquet"


def _read_sidecar(fs, path: str, max_rays: int | None) -> list[dict] | None:
    """The rows of a sidecar file written with the same max_rays, None when absent or different."""
    if not fs.exists(path):
        return None
    with fs.open(path, "rb") as handle:
        table = pq.read_table(handle)
    meta = json.loads((table.schema.metadata or {}).get(b"nuplan_occ_qa", b"{}"))
    return table.to_pylist() if meta.get("max_rays") == max_rays else None


def sidecar_columns(root: str, tokens: np.ndarray, commit_ids: np.ndarray) -> dict[str, np.ndarray]:
    """The figure columns of the dataset's sidecar files for frames given by token and manifest commit_id:
    float64 (N,) each, NaN where a frame has no row of that commit (never scored, or rebuilt since); {} when
    the dataset has no sidecar file."""
    import pyarrow.dataset

    fs, base = resolve(root)
    folder = f"{base}/{QA_FOLDER}"
    if not fs.exists(folder):
        return {}
    table = pyarrow.dataset.dataset(folder, format="parquet", filesystem=arrow_filesystem(fs)).to_table(
        columns=["token", "commit_id", *FIGURES])
    if not table.num_rows:
        return {}
    found = {key: i for i, key in enumerate(zip(table["token"].to_pylist(), table["commit_id"].to_pylist()))}
    rows = np.array([found.get((str(t), str(c)), -1) for t, c in zip(tokens, commit_ids)], dtype=np.int64)
    out = {}
    for column in FIGURES:
        values = table[column].cast(pa.float64()).fill_null(np.nan).to_numpy(zero_copy_only=False)
        out[column] = np.where(rows >= 0, values[np.maximum(rows, 0)], np.nan)
    return out


def scene_tasks(root: str, pipeline: list, data_root: Path, maps_root: str | None, work_root: Path | None) -> list:
    """The build's scene tasks of the dataset at `root`: its params (dataset.json; an imported release: none)
    over the pipeline's defaults, the logs it holds, found under data_root; work_root: the build's work folder
    (default OUT/work)."""
    from nuplan_occ.io.data_root import maps_root_for, resolve_logs
    from nuplan_occ.pipeline.build import default_work_root, plan_tasks
    from nuplan_occ.pipeline.params import apply_overrides, default_params
    from nuplan_occ.storage.metadata import read_metadata

    metadata = read_metadata(root)
    built = {} if "release" in metadata else metadata.get("params", {})  # an imported release: the default load
    params = apply_overrides(default_params(pipeline), built, f"{root}/dataset.json")
    logs = sorted({log for log in open_dataset(root).column("log").to_pylist() if log})
    dbs = resolve_logs(data_root, split=None, log_names=logs)
    return plan_tasks(dbs, Path(data_root), maps_root_for(data_root, maps_root), root,
                      Path(work_root) if work_root else default_work_root(root), params)


def qa_dataset(root: str, data_root: Path, pipeline: list, *, maps_root: str | None = None,
               work_root: Path | None = None, max_rays: int | None = MAX_RAYS, force: bool = False,
               progress: Callable[[int, int, str], None] | None = None) -> QaResult:
    """Score every ok frame of the dataset at `root` (module docstring) and write the sidecar files; a scene
    whose file holds the same frames and commits (and max_rays) is reused unless `force`."""
    ds = open_dataset(root)
    by_scene = scene_frames(ds)
    fs, base = resolve(root)
    result = QaResult()
    tasks = [t for t in scene_tasks(root, pipeline, data_root, maps_root, work_root)
             if (t.log_name, t.scene_token) in by_scene]
    for k, task in enumerate(tasks):
        if progress is not None:
            progress(k, len(tasks), task.scene_name)
        frames = by_scene[(task.log_name, task.scene_token)]
        path = _sidecar_path(base, task.log_name, task.scene_name)
        rows = None if force else _read_sidecar(fs, path, max_rays)
        if rows is not None and {(r["token"], r["commit_id"]) for r in rows} == \
                {(token, f["commit_id"]) for token, f in frames.items()}:
            result.reused += 1
        else:
            rows = score_scene(task, pipeline, frames, lambda token: ds.get(ds.index_of_token(token),
                                                                            keys=("semantics",))["semantics"],
                               max_rays, ds.grid, "release" not in ds.metadata)
            table = pa.Table.from_pylist(rows, schema=SCHEMA).replace_schema_metadata(
                {"nuplan_occ_qa": json.dumps({"max_rays": max_rays})})
            fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
            atomic_put(fs, path, to_parquet_bytes(table))
            result.scored += 1
        result.rows.extend(rows)
        scored = [r for r in rows if not r["qa_ray_problem"]]
        share = sum(bool(r["qa_ray_flags"]) for r in scored) / len(scored) if scored else 0.0
        if share > SCENE_RULE_SHARE:
            result.flagged_scenes[f"{task.log_name}/{task.scene_name}"] = share
    if progress is not None:
        progress(len(tasks), len(tasks), "")
    return result
