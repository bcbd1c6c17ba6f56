"""`make bench-scale`: the real-scale yardstick. `city` logs of one scene spanning the whole log (5 s, 10 s,
20 s: 50 / 100 / 200 output frames, ~135 k points per sweep), each built from scratch by one worker on one
core, in a child process whose RSS is sampled every 0.1 s and attributed to the stage running at the time.

Per scene length: seconds per output frame per stage and in all, peak RSS per stage and overall,
work-folder and dataset bytes per frame, and quality against the synthetic truth side by side with the
paper's method (benchmarks.small.bench_quality). With --baseline REV the same inputs are also built by the
code of git revision REV (exported next to the data), so before/after figures come from one run.
Writes bench/report-scale.json and bench/report-scale.md; synthesized logs are cached under bench/scale/.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tarfile
import threading
import time
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np

from nuplan_occ import __version__
from nuplan_occ.stages import PIPELINE
from benchmarks.small import BENCH_SEED, _table, bench_quality
from benchmarks.scale_plot import plot_stage_history, stage_history

SCALE_PRESET = "city"
RSS_SAMPLE_S = 0.1

_CHILD = """
import json, sys, time
from pathlib import Path
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.pipeline.params import default_params
try:
    from nuplan_occ.stages import PIPELINE
    dag = {"pipeline": PIPELINE}
except ImportError:  # revisions before the stages moved into the package take no pipeline argument
    from stages import PIPELINE
    dag = {}

def on_event(event):
    print(json.dumps({"cpu": time.process_time(), "stage": event[2]}), flush=True)

summary = run_build(Path(sys.argv[1]), sys.argv[2], default_params(PIPELINE), workers=1, on_event=on_event, **dag)
print(json.dumps({"summary": summary.to_dict()}), flush=True)
"""
"""The build a child runs: only `run_build`'s public signature, so older revisions run it unchanged (those
before the stages moved into the package: top-level `stages`, no pipeline argument)."""


def scale_data(cache: Path, seconds: float) -> Path:
    """The synthesized `city` log of `seconds` (one scene, truth at 10 Hz), made once under `cache`."""
    from nuplan_occ.synth.generate import synthesize

    root = cache / f"data_{seconds:g}s"
    done = root / ".complete"
    if not done.exists():
        shutil.rmtree(root, ignore_errors=True)
        synthesize(root, logs=1, seconds=seconds, seed=BENCH_SEED, preset=SCALE_PRESET, scene_seconds=seconds,
                   truth_rate_hz=10.0)
        done.touch()
    return root


def export_revision(rev: str, dest: Path) -> Path:
    """The source tree of git revision `rev` (of the repository holding this package) under dest/<rev>."""
    repo = Path(__file__).resolve().parents[1]
    target = dest / rev
    if not (target / "nuplan_occ").exists():
        shutil.rmtree(target, ignore_errors=True)
        archive = subprocess.run(["git", "-C", str(repo), "archive", "--format=tar", rev], check=True,
                                 capture_output=True).stdout
        with tarfile.open(fileobj=BytesIO(archive)) as tar:
            tar.extractall(target, filter="data")
    return target


@dataclass
class MemoryTrace:
    """RSS samples of a child build, peak overall and per stage (the stage that was running), and the CPU
    seconds each stage took (from the child's process time at each stage start: a per-core figure that
    other jobs on a shared machine do not inflate)."""

    peak_mb: float = 0.0
    stage_peak_mb: dict[str, float] = field(default_factory=dict)
    stage_cpu_s: dict[str, float] = field(default_factory=dict)
    stage: str = "start"
    cpu_mark: float = 0.0
    killed: str = ""

    def enter(self, stage: str, cpu_s: float) -> None:
        """The child started `stage` at process time cpu_s."""
        self.stage_cpu_s[self.stage] = self.stage_cpu_s.get(self.stage, 0.0) + cpu_s - self.cpu_mark
        self.stage, self.cpu_mark = stage, cpu_s


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def timed_build(data_root: Path, out: Path, source: Path, limit_mb: float) -> dict[str, Any]:
    """Build `data_root` into `out` (from scratch) with the code under `source`, one worker, one thread;
    the child is killed when its RSS passes limit_mb (the result then says so)."""
    shutil.rmtree(out, ignore_errors=True)
    env = {**os.environ, "PYTHONPATH": str(source), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    started = time.monotonic()
    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(data_root), str(out)], env=env, cwd=str(source),
                             stdout=subprocess.PIPE, text=True)
    trace, summary = MemoryTrace(), {}

    def read_events() -> None:
        nonlocal summary
        for line in child.stdout:  # type: ignore[union-attr]
            if not line.startswith("{"):
                continue
            message = json.loads(line)
            if "stage" in message:
                trace.enter(message["stage"], message["cpu"])
            else:
                summary = message["summary"]

    reader = threading.Thread(target=read_events, daemon=True)
    reader.start()
    while child.poll() is None:
        rss = _rss_mb(child.pid)
        trace.peak_mb = max(trace.peak_mb, rss)
        trace.stage_peak_mb[trace.stage] = max(trace.stage_peak_mb.get(trace.stage, 0.0), rss)
        if rss > limit_mb:
            trace.killed = f"killed at {rss:.0f} MB RSS during {trace.stage} (limit {limit_mb:.0f} MB)"
            child.kill()
        time.sleep(RSS_SAMPLE_S)
    reader.join(timeout=10)
    wall = time.monotonic() - started
    frames = max(int(summary.get("frames_built", 0)), 1)
    work = out / "work"
    work_bytes = sum(p.stat().st_size for p in work.rglob("*") if p.is_file()) if work.exists() else 0
    stage_seconds = summary.get("stage_seconds", {})
    cpu = {k: v for k, v in trace.stage_cpu_s.items() if k not in ("start", "done")}
    return {
        "cpu_seconds_per_frame": sum(cpu.values()) / frames,
        "stage_cpu_seconds_per_frame": {k: v / frames for k, v in cpu.items()},
        "ok": child.returncode == 0 and not trace.killed, "killed": trace.killed, "wall_seconds": wall,
        "frames_built": summary.get("frames_built", 0), "frames_failed": summary.get("frames_failed", 0),
        "seconds_per_frame": sum(stage_seconds.values()) / frames,
        "wall_seconds_per_frame": wall / frames,
        "stage_seconds_per_frame": {k: v / frames for k, v in stage_seconds.items()},
        "peak_rss_mb": trace.peak_mb, "stage_peak_rss_mb": trace.stage_peak_mb,
        "work_bytes_per_frame": work_bytes / frames, "dataset_bytes_per_frame": summary.get("bytes_per_frame", 0.0),
    }


def code_label(repo: Path) -> str:
    """Short commit hash of the working tree, with "+changes" when it differs from the commit."""
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return (head.stdout.strip() or "unknown") + ("+changes" if dirty else "")


def median_build(builds: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from repeated timed builds of the same code on the same input: the median of every cost
    figure (CPU, stage and wall seconds, per stage too, and peak RSS), each build's CPU s/frame in
    `cpu_seconds_per_frame_builds`; ok only when every build was. Byte counts and frame counts are the
    first build's (builds are deterministic)."""
    row = dict(builds[0])
    for key in ("cpu_seconds_per_frame", "seconds_per_frame", "wall_seconds_per_frame", "wall_seconds", "peak_rss_mb"):
        row[key] = float(np.median([b[key] for b in builds]))
    for key in ("stage_cpu_seconds_per_frame", "stage_seconds_per_frame", "stage_peak_rss_mb"):
        stages = {s for b in builds for s in b[key]}
        row[key] = {s: float(np.median([b[key][s] for b in builds if s in b[key]])) for s in stages}
    row["ok"] = all(b["ok"] for b in builds)
    row["killed"] = next((b["killed"] for b in builds if b["killed"]), "")
    row["cpu_seconds_per_frame_builds"] = [b["cpu_seconds_per_frame"] for b in builds]
    return row


def run_scale_bench(out_dir: Path, seconds: list[float], baseline: str | None, limit_mb: float,
                    quality_stride: int, baseline_max_seconds: float, repeats: int = 1) -> dict[str, Any]:
    """Every scene length built by this code (and by `baseline` up to baseline_max_seconds) `repeats` times,
    the codes' builds interleaved (this, baseline, this, ...) so that a machine whose speed drifts slows both
    alike; each row is their `median_build`, the quality that of this code's last build. Returns the report.
    Rows of other code versions already in bench/report-scale.json are kept (each row has its date), and so
    are its notes and its KISS-ICP measurement (a run that skips it keeps the last one)."""
    cache = out_dir.resolve() / "scale"  # absolute: the baseline's builds run from its exported source
    cache.mkdir(parents=True, exist_ok=True)
    here = Path(__file__).resolve().parents[1]
    this = code_label(here)
    previous = out_dir / "report-scale.json"
    earlier = json.loads(previous.read_text()) if previous.exists() else {"runs": []}
    kept = [r for r in earlier["runs"] if r["code"] != this]
    report: dict[str, Any] = {"software": f"nuplan-occ {__version__}", "machine": platform.machine(),
                              "cpus": os.cpu_count(), "preset": SCALE_PRESET, "seed": BENCH_SEED,
                              "quality_frame_stride": quality_stride, "runs": kept,
                              **{k: earlier[k] for k in ("notes", "kiss_icp") if k in earlier}}
    for length in seconds:
        data_root = scale_data(cache, length)
        builds = [(this, here)]
        if baseline and length <= baseline_max_seconds:
            builds.append((baseline, export_revision(baseline, cache / "src")))
        date = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        out = {name: cache / f"build_{length:g}s_{name}" for name, _ in builds}
        timed: dict[str, list[dict[str, Any]]] = {name: [] for name, _ in builds}
        for repeat in range(repeats):
            for name, source in builds:
                print(f"bench-scale: {length:g} s scene, code {name}, build {repeat + 1} of {repeats} ...", flush=True)
                timed[name].append(timed_build(data_root, out[name], source, limit_mb))
        for name, _ in builds:
            row = {"seconds": length, "code": name, "date": date, **median_build(timed[name])}
            report["runs"] = [r for r in report["runs"] if (r["seconds"], r["code"]) != (length, name)]
            if row["ok"] and name == this:
                row["quality"] = bench_quality(data_root, out[name], frame_stride=quality_stride)
            report["runs"].append(row)
            write_scale_report(report, out_dir)
    return report


def bench_kiss_icp(data_root: Path, sweeps: int, threads: tuple[int, ...] = (1, 0)) -> dict[str, Any]:
    """KISS-ICP odometry (the declared dependency) on the first `sweeps` merged sweeps of the scale log, ego
    frame, voxel 1 m: seconds per sweep and whether two runs give bit-identical poses, per thread count
    (0 = all cores); plus the drift of its trajectory from the logged poses (m, over the run)."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    from nuplan_occ.geometry import invert_transform
    from nuplan_occ.io.data_root import resolve_logs, sensor_root_for
    from nuplan_occ.io.reader import NuplanLog

    db = resolve_logs(data_root)[0]
    with NuplanLog(db, sensor_root_for(db, data_root)) as log:
        frames = log.frames[:sweeps]
        T_ego_from_lidar = log.lidar.T_ego_from_lidar
        clouds = [log.load_points(f).transformed(T_ego_from_lidar, "ego").xyz for f in frames]
        logged = np.stack([log.frame_pose(f) for f in frames])
    out: dict[str, Any] = {"sweeps": len(clouds), "points_per_sweep": float(np.mean([len(c) for c in clouds]))}
    for count in threads:
        runs = []
        for _ in range(2):
            config = KISSConfig()
            config.mapping.voxel_size = 1.0
            config.data.deskew = False
            config.registration.max_num_threads = count
            odometry = KissICP(config)
            started = time.process_time() if count == 1 else time.perf_counter()
            poses = []
            for cloud in clouds:
                odometry.register_frame(np.ascontiguousarray(cloud, dtype=np.float64), np.zeros(0))
                poses.append(odometry.last_pose.copy())
            elapsed = (time.process_time() if count == 1 else time.perf_counter()) - started
            runs.append((np.stack(poses), elapsed / len(clouds)))
        logged_rel = np.einsum("ij,njk->nik", invert_transform(logged[0]), logged)
        out[f"threads_{count}"] = {
            "seconds_per_sweep": min(r[1] for r in runs),
            "identical_runs": bool(np.array_equal(runs[0][0], runs[1][0])),
            "max_pose_difference_m": float(np.abs(runs[0][0][:, :3, 3] - runs[1][0][:, :3, 3]).max()),
            "end_offset_from_log_m": float(np.linalg.norm(runs[0][0][-1, :3, 3] - logged_rel[-1, :3, 3])),
        }
    return out


PICTURE_SCENE_SECONDS = 20.0
"""The scene length whose builds the report's picture shows (the length the targets are set for)."""
PICTURE_NAME = "report-scale.png"


def write_scale_report(report: dict, out_dir: Path) -> None:
    """bench/report-scale.json, bench/report-scale.md and its picture bench/report-scale.png."""
    (out_dir / "report-scale.json").write_text(json.dumps(report, indent=2, default=float))
    history = stage_history(report, PICTURE_SCENE_SECONDS, STAGE_ORDER)
    if history.labels:
        plot_stage_history(history, PICTURE_SCENE_SECONDS, out_dir / PICTURE_NAME)
    (out_dir / "report-scale.md").write_text(render_scale_markdown(report, picture=bool(history.labels)))


def _build_note(row: dict) -> str:
    """The cost table's note: why a build was killed, and each build's CPU s/frame when a row is a median."""
    builds = row.get("cpu_seconds_per_frame_builds", [])
    spread = f"median of {len(builds)} interleaved builds: " + " / ".join(f"{b:.3f}" for b in builds) if len(builds) > 1 else ""
    return "; ".join(part for part in (row["killed"], spread) if part)


def render_scale_markdown(report: dict, picture: bool = False) -> str:
    """The scale report as Markdown tables; with `picture`, led by bench/report-scale.png."""
    runs = report["runs"]
    stages = sorted({s for r in runs for s in r["stage_seconds_per_frame"]} | {s for r in runs for s in r["stage_peak_rss_mb"]},
                    key=lambda s: [*STAGE_ORDER, s].index(s))
    parts = [f"# nuplan-occ scale bench ({report['software']}, {report['machine']}, {report['cpus']} cpus)", "",
             f"Synthetic `{report['preset']}` logs (seed {report['seed']}), one scene spanning the log, one worker on one "
             "thread, built from scratch. Targets: <= 1.0 s per frame per core and peak RSS <= 6 GB "
             "for the 20 s scene (<= 1.3x the 5 s scene's).", "",
             *([f"![CPU seconds per frame by stage and peak RSS of every {PICTURE_SCENE_SECONDS:g} s build]"
                f"({PICTURE_NAME})", ""] if picture else []),
             "## Cost", "",
             _table(["scene s", "code", "date", "frames", "failed", "CPU s/frame", "stage wall s/frame", "wall s/frame", "peak RSS MB",
                     "work bytes/frame", "dataset bytes/frame", "note"],
                    [[r["seconds"], r["code"], r["date"], r["frames_built"], r["frames_failed"],
                      r.get("cpu_seconds_per_frame", float("nan")), r["seconds_per_frame"],
                      r["wall_seconds_per_frame"], r["peak_rss_mb"], r["work_bytes_per_frame"],
                      r["dataset_bytes_per_frame"], _build_note(r)] for r in runs]), "",
             "## CPU seconds per output frame, per stage (one thread)", "",
             _table(["scene s", "code", *stages], [[r["seconds"], r["code"], *[r.get("stage_cpu_seconds_per_frame", {}).get(s, "")
                                                     for s in stages]] for r in runs]), "",
             "## Wall seconds per output frame, per stage (inflated when the machine is shared)", "",
             _table(["scene s", "code", *stages], [[r["seconds"], r["code"], *[r["stage_seconds_per_frame"].get(s, "")
                                                     for s in stages]] for r in runs]), "",
             "## Peak RSS (MB) while each stage ran", "",
             _table(["scene s", "code", *stages], [[r["seconds"], r["code"], *[r["stage_peak_rss_mb"].get(s, "")
                                                     for s in stages]] for r in runs]), ""]
    rows = [r for r in runs if "quality" in r]
    if rows:
        classes = sorted({c for r in rows for m in ("ours", "paper_method") for c in r["quality"][m]["per_class_iou"]})
        parts += [f"## Quality against truth (inside the truth's mask_lidar, median over every "
                  f"{report['quality_frame_stride']}th frame)", "",
                  "Targets: IoU >= 0.90, mIoU >= 0.80, every class >= 0.5, zero trails, each better than the paper's method.",
                  "", _table(["scene s", "code", "method", "frames", "IoU", "mIoU", "trail voxels", "ground hole rate", *classes],
                             [[r["seconds"], r["code"], m, r["quality"]["frames"], r["quality"][m]["iou"], r["quality"][m]["miou"],
                               r["quality"][m]["trail_voxels_total"], r["quality"][m]["ground_hole_rate"],
                               *[r["quality"][m]["per_class_iou"].get(c, float("nan")) for c in classes]]
                              for r in rows for m in ("ours", "paper_method")]), ""]
        pooled = [r for r in rows if "pooled" in r["quality"]["ours"]]
        if pooled:
            parts += ["Pooled over the same frames (one confusion summed over them, as `nuplan-occ eval` counts):", "",
                      _table(["scene s", "code", "method", "IoU", "mIoU", *classes],
                             [[r["seconds"], r["code"], m, r["quality"][m]["pooled"]["iou"], r["quality"][m]["pooled"]["miou"],
                               *[r["quality"][m]["pooled"]["per_class_iou"].get(c, float("nan")) for c in classes]]
                              for r in pooled for m in ("ours", "paper_method")]), ""]
        annotated = [r for r in rows if "pooled_annotated" in r["quality"]["ours"]]
        if annotated:
            parts += ["Pooled over the same frames without the truth voxels of objects the log has no box for (the "
                      "synthetic log leaves one moving object unboxed on purpose; no method reading boxes can class "
                      "it; `nuplan_occ.evaluation.grid_metrics.unannotated_objects`):", "",
                      _table(["scene s", "code", "method", "IoU", "mIoU", *classes],
                             [[r["seconds"], r["code"], m, r["quality"][m]["pooled_annotated"]["iou"],
                               r["quality"][m]["pooled_annotated"]["miou"],
                               *[r["quality"][m]["pooled_annotated"]["per_class_iou"].get(c, float("nan"))
                                 for c in classes]]
                              for r in annotated for m in ("ours", "paper_method")]), ""]
    if report.get("kiss_icp"):
        k = report["kiss_icp"]
        parts += [f"## KISS-ICP odometry as a registration front end ({k['sweeps']} sweeps of the 5 s log, "
                  f"{k['points_per_sweep']:.0f} points each, voxel 1 m)", "",
                  _table(["threads (0 = all)", "s per sweep", "two runs identical", "max difference m",
                          "end offset from log m"],
                         [[name.split("_")[1], v["seconds_per_sweep"], v["identical_runs"], v["max_pose_difference_m"],
                           v["end_offset_from_log_m"]] for name, v in k.items() if name.startswith("threads_")]), ""]
    if report.get("recorded_baseline"):
        b = report["recorded_baseline"]
        parts += ["## Recorded baseline (not rerun here)", "", b["text"], ""]
    if report.get("notes"):
        parts += ["## Notes", "", *[f"- {note}" for note in report["notes"]], ""]
    return "\n".join(parts)


STAGE_ORDER = ["start", *(stage.name for stage in PIPELINE), "done"]

RECORDED_BASELINE = {
    "text": "Measured 2026-12-01 on commit 4ae3972: 10 s `city` scene (100 output frames, "
            "135 k points per sweep, 107 agents), `nuplan-occ build --workers 1`: wall 1315 s = 13.2 s per frame "
            "on one core (visibility 4.0, aggregate 2.8, voxelize 2.1, register 1.2, filter 0.6, reconstruct 0.6, "
            "track 0.5, write 0.4, label 0.3 s per frame); peak RSS 13.0 GB; IoU 0.942, mIoU 0.627 (traffic_cone "
            "0.00, czone_sign 0.28, vehicle 0.43, pedestrian 0.53).",
    "seconds_per_frame": 13.2, "peak_rss_mb": 13000.0, "scene_seconds": 10.0,
}
"""The figures of the code before the scale work (commit 4ae3972), kept with their date where a rerun is too
heavy."""


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench"))
    parser.add_argument("--seconds", type=float, nargs="+", default=[5.0, 10.0, 20.0])
    parser.add_argument("--baseline", default=None, help="git revision built side by side on the same inputs")
    parser.add_argument("--baseline-max-seconds", type=float, default=5.0,
                        help="longest scene the baseline builds (its memory grows with scene length)")
    parser.add_argument("--limit-mb", type=float, default=10_000.0, help="kill a build whose RSS passes this")
    parser.add_argument("--quality-stride", type=int, default=2, help="measure quality on every n-th frame")
    parser.add_argument("--kiss-sweeps", type=int, default=60, help="sweeps of the KISS-ICP measurement (0 = skip)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="builds per code and scene, interleaved with the baseline's; rows give their medians")
    args = parser.parse_args(argv)
    if args.kiss_sweeps:
        kiss = bench_kiss_icp(scale_data(args.out / "scale", 5.0), args.kiss_sweeps)
    report = run_scale_bench(args.out, args.seconds, args.baseline, args.limit_mb, args.quality_stride,
                             args.baseline_max_seconds, args.repeats)
    report["recorded_baseline"] = RECORDED_BASELINE
    if args.kiss_sweeps:
        report["kiss_icp"] = kiss
    write_scale_report(report, args.out)
    print((args.out / "report-scale.md").read_text())


if __name__ == "__main__":
    main()
