"""`make bench-real-size`: opening and loading a log of a real log's size.

A real 20-minute nuPlan log holds about 24 k lidar_pc, 119 k ego_pose, 2.6 M lidar_box and 96 k image rows
in 65 scenes, and its DB declares no index on lidar_box.lidar_pc_token. The bench writes one 20 s scene
with the project's nuPlan writer (100 Hz ego poses, 108 boxes per sweep, 8 cameras at 10 Hz, small PCDs)
and inflates it inside SQLite to 65 scenes (each copy shifted by 20 s, tokens made unique), without any
index. Each code version then, in a fresh child process: opens the log (seconds, RSS growth), runs the
load stage on a few scenes (seconds per scene, sweeps' PCDs included but tiny), and reports its peak RSS;
the same child on the one-scene 20 s log gives the peak a real-size log must not exceed.

The code before is exported with `git archive` (default: the revision before the reader's rework) into a
folder of its own and imported from there. Writes bench/report-real-size-log.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SCENE_SECONDS = 20.0
COPIES = 65
BOXES_PER_SWEEP = 108
POINTS_PER_SWEEP = 2000
BASELINE = "ff24e0e"
"""The last revision before the reader read tables as columns and boxes per scene."""

_CHILD = """
import json, resource, sys, time
sys.path.insert(0, sys.argv[1])
from pathlib import Path
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.pipeline.scene import SceneTask
from nuplan_occ.stages import load

db, blobs, work, n_scenes = Path(sys.argv[2]), sys.argv[3], sys.argv[4], int(sys.argv[5])
def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
before = rss_mb()
started, cpu = time.perf_counter(), time.process_time()
log = NuplanLog(db, blobs)
open_s, open_cpu_s = time.perf_counter() - started, time.process_time() - cpu
open_mb = rss_mb() - before
scenes = [s for s in log.scenes if log.frames_of_scene(s.token)][:n_scenes]
counts = {"lidar_pc": len(log.frames), "scenes": len(log.scenes)}
log.close()
del log
times, cpu_times = [], []
for scene in scenes:
    task = SceneTask(str(db), blobs, str(Path(work) / "maps"), "bench", 1, scene.token, scene.name,
                     str(Path(work) / "out"), str(Path(work) / "work"), {})
    started, cpu = time.perf_counter(), time.process_time()
    out = load.run({"task": task}, load.LoadParams())
    times.append(time.perf_counter() - started)
    cpu_times.append(time.process_time() - cpu)
    assert out["scene"].sweeps
    del out
print(json.dumps({"open_s": open_s, "open_cpu_s": open_cpu_s, "open_mb": open_mb, "load_s": times,
                  "load_cpu_s": cpu_times, "peak_mb": rss_mb(), **counts}))
"""


def write_base_log(root: Path) -> Path:
    """One 20 s scene written by the project's nuPlan writer (no box index); returns the DB path."""
    from nuplan_occ.geometry import make_transform, yaw_matrix
    from nuplan_occ.io.types import (
        LIDAR_CHANNEL, Boxes, CameraCalibration, EgoPoseRecord, ImageRecord, LidarCalibration, LidarFrame,
        LogContent, LogMeta, PointCloud, SceneRecord, TrackRecord,
    )
    from nuplan_occ.io.writer import new_token, write_log

    rng = np.random.default_rng(0)
    t0 = 1_620_000_000_000_000
    logfile = "2021.05.12.22.00.38_veh-35_00001_01300"
    meta = LogMeta(new_token(rng), logfile, "veh-35", "2021-05-12", t0, "las_vegas", "us-nv-las-vegas-strip")
    lidar = LidarCalibration(new_token(rng), LIDAR_CHANNEL, "merged", make_transform(np.eye(3), [1.5, 0, 1.6]))
    cameras = [CameraCalibration(new_token(rng), f"CAM_{k}", "cam", np.array([[500, 0, 240], [0, 500, 135], [0, 0, 1.0]]),
                                 np.zeros(5), make_transform(yaw_matrix(k * np.pi / 4), [1, 0, 1.5]), 480, 270)
               for k in range(8)]

    def pose(t_us: int) -> np.ndarray:
        s = (t_us - t0) / 1e6
        return make_transform(yaw_matrix(0.01 * s), [664_000 + 8.0 * s, 3_997_000 + 0.5 * s, 600.0])

    ego_times = range(t0, t0 + int(SCENE_SECONDS * 1e6) + 1, 10_000)
    ego_poses = [EgoPoseRecord(new_token(rng), t, pose(t)) for t in ego_times]
    scene = SceneRecord(new_token(rng), "scene-0000")
    frame_times = range(t0, t0 + int(SCENE_SECONDS * 1e6), 50_000)
    frames = [LidarFrame(tok := new_token(rng), t, f"{logfile}/{LIDAR_CHANNEL}/{tok}.pcd", scene.token,
                         ego_poses[(t - t0) // 10_000].token, lidar.token, index=i) for i, t in enumerate(frame_times)]
    tracks = [TrackRecord(new_token(rng), "vehicle", 2.0, 4.5, 1.7) for _ in range(BOXES_PER_SWEEP)]
    offsets = rng.uniform(-60, 60, (BOXES_PER_SWEEP, 3)) * [1, 1, 0]
    boxes = {}
    for f in frames:
        centers = pose(f.timestamp_us)[:3, 3] + offsets
        boxes[f.token] = Boxes("global", centers, np.tile([4.5, 2.0, 1.7], (BOXES_PER_SWEEP, 1)),
                               np.zeros(BOXES_PER_SWEEP), np.zeros((BOXES_PER_SWEEP, 3)), ["vehicle"] * BOXES_PER_SWEEP,
                               [t.token for t in tracks], [new_token(rng) for _ in tracks])
    images = [ImageRecord(new_token(rng), t, f"{logfile}/{cam.channel}/{k}.jpg", cam.token,
                          ego_poses[(t - t0) // 10_000].token)
              for k, t in enumerate(range(t0, t0 + int(SCENE_SECONDS * 1e6), 100_000)) for cam in cameras]
    content = LogContent(meta, lidar, cameras, ego_poses, [scene], frames, tracks, boxes, images)
    xyz = rng.uniform(-40, 40, (POINTS_PER_SWEEP, 3))
    cloud = PointCloud(xyz, np.ones(POINTS_PER_SWEEP, np.float32), np.zeros(POINTS_PER_SWEEP, np.int16),
                       np.zeros(POINTS_PER_SWEEP, np.int8), "lidar")
    return write_log(content, root, point_source=lambda frame: cloud)


def inflate(base_db: Path, out_db: Path, copies: int) -> None:
    """out_db = base_db with its scene, lidar_pc, ego_pose, lidar_box and image rows repeated `copies` times,
    copy k shifted by k scene lengths and its tokens suffixed with k (PCD filenames shared); no index."""
    out_db.write_bytes(base_db.read_bytes())
    shift = int(SCENE_SECONDS * 1e6)
    suffix = "CAST({0} || printf('%03d', {1}) AS BLOB)"

    def tok(column: str, k: str = ":k") -> str:
        return f"CASE WHEN {column} IS NULL THEN NULL ELSE {suffix.format(column, k)} END"

    db = sqlite3.connect(out_db)
    with db:
        for table in ("scene", "lidar_pc", "ego_pose", "lidar_box", "image"):
            db.execute(f"CREATE TEMP TABLE base_{table} AS SELECT * FROM {table}")
            db.execute(f"DELETE FROM {table}")
        for k in range(copies):
            p = {"k": k, "dt": k * shift}
            db.execute(f"INSERT INTO scene (token, log_token, name, goal_ego_pose_token, roadblock_ids) SELECT "
                       f"{tok('token')}, log_token, printf('scene-%04d', :k), {tok('goal_ego_pose_token')}, "
                       "roadblock_ids FROM base_scene", p)
            db.execute(f"INSERT INTO ego_pose SELECT {tok('token')}, timestamp + :dt, x + 160.0 * :k, y, z, qw, qx, "
                       "qy, qz, vx, vy, vz, acceleration_x, acceleration_y, acceleration_z, angular_rate_x, "
                       "angular_rate_y, angular_rate_z, epsg, log_token FROM base_ego_pose", p)
            db.execute(f"INSERT INTO lidar_pc SELECT {tok('token')}, {tok('next_token')}, {tok('prev_token')}, "
                       f"{tok('ego_pose_token')}, lidar_token, {tok('scene_token')}, filename, timestamp + :dt "
                       "FROM base_lidar_pc", p)
            db.execute(f"INSERT INTO lidar_box SELECT {tok('token')}, {tok('lidar_pc_token')}, track_token, "
                       f"{tok('next_token')}, {tok('prev_token')}, x + 160.0 * :k, y, z, width, length, height, vx, "
                       "vy, vz, yaw, confidence FROM base_lidar_box", p)
            db.execute(f"INSERT INTO image SELECT {tok('token')}, {tok('next_token')}, {tok('prev_token')}, "
                       f"{tok('ego_pose_token')}, camera_token, filename_jpg, timestamp + :dt FROM base_image", p)
    db.close()


def measure(code_root: Path, db: Path, blobs: Path, work: Path, n_scenes: int) -> dict:
    result = subprocess.run([sys.executable, "-c", _CHILD, str(code_root), str(db), str(blobs), str(work),
                             str(n_scenes)], capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def export_revision(rev: str, folder: Path) -> Path:
    """The package as of git revision `rev`, unpacked under `folder` (kept between runs)."""
    target = folder / rev
    if not (target / "nuplan_occ").is_dir():
        target.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", rev, "nuplan_occ"], capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
    return target


def report(rows: dict, counts: dict, generation_s: float, db_mb: float) -> str:
    def fmt(r: dict) -> list[str]:
        loads, cpu = r["load_s"], r["load_cpu_s"]
        return [f"{r['open_s']:.2f} / {r['open_cpu_s']:.2f}", f"{r['open_mb']:.0f}",
                f"{np.median(loads):.2f} / {np.median(cpu):.2f}", " ".join(f"{c:.2f}" for c in cpu),
                f"{r['peak_mb']:.0f}"]

    lines = ["# Opening and loading a real-size log", "",
             f"Inflated log: {counts['scenes']} scenes of {SCENE_SECONDS:g} s, {counts['lidar_pc']} lidar_pc, "
             f"{counts['ego_pose']} ego_pose, {counts['lidar_box']} lidar_box, {counts['image']} image rows; "
             f"{db_mb:.0f} MB; no index on lidar_box.lidar_pc_token; generated in {generation_s:.0f} s. "
             f"PCDs hold {POINTS_PER_SWEEP} points, so load time is the DB's.", "",
             "Times are wall / CPU seconds in a child process on a machine shared with other jobs (CPU seconds are "
             "the steadier figure); the first scene's load includes opening the log (one open per worker).", "",
             "| code | log | open s (wall / CPU) | open +MB | load s per 20 s scene, median (wall / CPU) | "
             "load CPU s per scene | peak RSS MB |",
             "|---|---|---|---|---|---|---|"]
    for (code, log), r in rows.items():
        lines.append("| " + " | ".join([code, log, *fmt(r)]) + " |")
    lines += ["", f"Machine load average while measuring: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores.", "",
              "Targets: open <= 1 s; load <= 1 s per 20 s scene; peak RSS on the real-size log no higher "
              "than on the 20 s log.", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=Path("bench/real_size"))
    parser.add_argument("--baseline", default=BASELINE)
    parser.add_argument("--scenes", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("bench"))
    args = parser.parse_args()
    work = args.work.resolve()
    base_db = next(work.glob("base/**/*.db"), None)
    started = time.perf_counter()
    if base_db is None:
        base_db = write_base_log(work / "base")
    big_db = work / "real_size.db"
    if not big_db.is_file():
        inflate(base_db, big_db, COPIES)
    generation_s = time.perf_counter() - started
    db = sqlite3.connect(big_db)
    counts = {t: db.execute(f"SELECT count(*) FROM {t}").fetchone()[0]
              for t in ("scene", "lidar_pc", "ego_pose", "lidar_box", "image")}
    db.close()
    counts["scenes"] = counts.pop("scene")
    blobs = work / "base" / "nuplan-v1.1" / "sensor_blobs"
    codes = {"after": Path(__file__).resolve().parents[1],
             f"before ({args.baseline})": export_revision(args.baseline, work / "code")}
    rows = {}
    for name, root in codes.items():
        for log, path, n in (("20 s", base_db, 1), ("real size", big_db, args.scenes)):
            rows[(name, log)] = measure(root, path, blobs, work, n)
            print(name, log, rows[(name, log)], flush=True)
    text = report(rows, counts, generation_s, big_db.stat().st_size / 1e6)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report-real-size-log.md").write_text(text)
    (args.out / "report-real-size-log.json").write_text(json.dumps(
        {"counts": counts, "rows": {f"{c} | {l}": r for (c, l), r in rows.items()}}, indent=2))
    print(text)


if __name__ == "__main__":
    main()
