"""`make bench-manifest`: the append-only manifest at dataset scale and the work-folder policies.
Writes bench/report-manifest.json and bench/report-manifest.md.

Sections:
- commit: time of one scene commit (190 rows) into a manifest of 1 k and 19 k simulated scenes
  (190 rows each, one fragment per scene), median over repeated commits;
- open: `open_dataset` over 3.6 M simulated rows (19 k fragments, then after `compact`): wall time and
  peak RSS of a fresh process, token lookup and random frame-identity reads, and the clip index of
  `OccupancyDataset`; compaction time;
- work: a real build of a synthetic log with `--keep-work all`: cache bytes per output frame of every
  stage, and the work folder per frame under each policy, next to the dataset's own bytes per frame.
Rows are simulated (`storage.simulated_manifest`); no shards exist for them.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq

from nuplan_occ import __version__
from nuplan_occ.storage import DatasetWriter
from nuplan_occ.storage.fragments import scene_dir
from nuplan_occ.storage.simulated_manifest import simulated_manifest

FRAMES_PER_SCENE = 190
SCENE_COUNTS = (1_000, 19_000)
COMMITS_PER_POINT = 15

OPEN_PROBE = r"""
import json, resource, sys, time
import numpy as np
from nuplan_occ.dataset import open_dataset
t0 = time.perf_counter()
ds = open_dataset(sys.argv[1])
opened = time.perf_counter() - t0
rng = np.random.default_rng(0)
picks = rng.integers(0, len(ds), 50)
tokens = [ds.column("token")[int(i)].as_py() for i in picks[:5]]
t = time.perf_counter(); found = [ds.index_of_token(tok) for tok in tokens]; lookup = (time.perf_counter() - t) / 5
assert found == [int(i) for i in picks[:5]]
t = time.perf_counter(); [ds.identity(int(i)) for i in picks]; identity = (time.perf_counter() - t) / len(picks)
print(json.dumps({"rows": len(ds), "open_s": opened, "token_lookup_ms": 1e3 * lookup, "identity_read_ms": 1e3 * identity,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

CLIPS_PROBE = r"""
import json, resource, sys, time
import torch
torch.set_num_threads(1)
from nuplan_occ.torch import OccupancyDataset
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t0 = time.perf_counter()
clips = OccupancyDataset(sys.argv[1], clip_len=8, stride=4, subset="spatial")
print(json.dumps({"clips": len(clips), "index_s": time.perf_counter() - t0,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rss_after_torch_import_mb": base}))
"""


def _probe(script: str, root: Path) -> dict[str, Any]:
    done = subprocess.run([sys.executable, "-c", script, str(root)], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _populate(root: Path, table, n_scenes: int, start: int) -> None:
    """Write scenes [start, n_scenes) of the simulated table as one fragment each."""
    for s in range(start, n_scenes):
        rows = table.slice(s * FRAMES_PER_SCENE, FRAMES_PER_SCENE)
        folder = Path(scene_dir(str(root), rows["log"][0].as_py(), rows["scene_token"][0].as_py()))
        folder.mkdir(parents=True, exist_ok=True)
        pq.write_table(rows, folder / f"{rows['commit_id'][0].as_py()}.parquet", compression="zstd")


def _commit_times(root: Path, n: int, seed: int) -> list[float]:
    """Seconds per commit of a fresh 190-row scene (its shard file exists, empty)."""
    writer = DatasetWriter(str(root), {"params": {}})
    times = []
    for k in range(COMMITS_PER_POINT):
        rows = simulated_manifest(1, FRAMES_PER_SCENE, seed=seed + k).drop_columns(["commit_id"])
        rows = rows.to_pylist()
        for row in rows:
            row["log"], row["shard"] = f"new-{seed}-{k}", f"new-{seed}-{k}/scene-0000"
        shard = root / "shards" / f"new-{seed}-{k}" / "scene-0000.tar"
        shard.parent.mkdir(parents=True, exist_ok=True)
        shard.write_bytes(b"")
        started = time.perf_counter()
        writer.commit(rows)
        times.append(time.perf_counter() - started)
    return times


def bench_commit_and_open(work: Path, scene_counts: tuple[int, ...] = SCENE_COUNTS) -> dict[str, Any]:
    from nuplan_occ.storage.compact import compact

    root = work / "manifest_scale"
    shutil.rmtree(root, ignore_errors=True)
    table = simulated_manifest(scene_counts[-1], FRAMES_PER_SCENE)
    out: dict[str, Any] = {"frames_per_scene": FRAMES_PER_SCENE, "commit": {}}
    done = 0
    for n in scene_counts:
        _populate(root, table, n, done)
        done = n
        times = _commit_times(root, n, seed=n)
        out["commit"][str(n)] = {"scenes": n, "rows": n * FRAMES_PER_SCENE, "median_s": statistics.median(times),
                                 "max_s": max(times)}
        for k in range(COMMITS_PER_POINT):  # keep the population at exactly n scenes for the next point
            shutil.rmtree(Path(scene_dir(str(root), f"new-{n}-{k}", "any")).parent, ignore_errors=True)
    small, large = (out["commit"][str(n)]["median_s"] for n in scene_counts)
    out["commit"]["ratio_19k_to_1k"] = large / small
    out["scene_counts"] = list(scene_counts)
    del table
    out["open_fragments"] = _probe(OPEN_PROBE, root)
    started = time.perf_counter()
    result = compact(str(root))
    out["compact"] = {"seconds": time.perf_counter() - started, "files_before": result.files_before,
                      "rows": result.rows_after, "bytes": Path(result.output).stat().st_size}
    out["open_compacted"] = _probe(OPEN_PROBE, root)
    out["clips_compacted"] = _probe(CLIPS_PROBE, root)
    shutil.rmtree(root, ignore_errors=True)
    return out


def _tree_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.exists() else 0


def bench_work(work: Path, seconds: float) -> dict[str, Any]:
    """A real build with every cache entry kept; bytes per output frame per stage and per policy."""
    from nuplan_occ.pipeline.build import run_build
    from nuplan_occ.pipeline.params import default_params
    from nuplan_occ.pipeline.publish import DEFAULT_KEPT_STAGES
    from nuplan_occ.synth.generate import synthesize
    from stages import PIPELINE

    data = work / "work_data"
    if not (data / "nuplan-v1.1").exists():
        synthesize(data, logs=1, seconds=seconds, seed=0, preset="small")
    out = work / "work_build"
    shutil.rmtree(out, ignore_errors=True)
    summary = run_build(data, str(out), default_params(PIPELINE), keep_work="all")
    frames = summary.frames_built + summary.frames_failed
    per_stage: dict[str, int] = {}
    for stage_dir in (out / "work").glob("*/*/*"):
        per_stage[stage_dir.name] = per_stage.get(stage_dir.name, 0) + _tree_bytes(stage_dir)
    dataset_bytes = _tree_bytes(out) - _tree_bytes(out / "work")
    policies = {"all": sum(per_stage.values()),
                "default": sum(v for k, v in per_stage.items() if k in DEFAULT_KEPT_STAGES), "none": 0}
    return {"log_seconds": seconds, "frames": frames, "build_wall_s": summary.wall_seconds,
            "stage_bytes_per_frame": {k: v / frames for k, v in sorted(per_stage.items())},
            "work_bytes_per_frame": {k: v / frames for k, v in policies.items()},
            "dataset_bytes_per_frame": dataset_bytes / frames}


def render_markdown(report: dict[str, Any]) -> str:
    lines = [f"# Manifest bench (nuplan-occ {report['software']}, {report['machine']})", ""]
    scale = report.get("scale")
    if scale:
        c = scale["commit"]
        lines += ["## Commit time of one scene (190 rows), one fragment per scene", "",
                  "| scenes in the manifest | rows | median s | max s |", "|---:|---:|---:|---:|"]
        for n in scale["scene_counts"]:
            row = c[str(n)]
            lines.append(f"| {row['scenes']:,} | {row['rows']:,} | {row['median_s']:.4f} | {row['max_s']:.4f} |")
        lines += ["", f"Ratio 19 k / 1 k: **{c['ratio_19k_to_1k']:.2f}** (target <= 1.5). Before (read, merge and "
                  "rewrite manifest.parquet; issue #17): 1.1 s at 190 k rows, 3.8 s at 760 k rows.", "",
                  "## Opening 3.6 M rows (fresh process)", "",
                  "| manifest | rows | open s | peak RSS MB | token lookup ms | frame identity ms |",
                  "|---|---:|---:|---:|---:|---:|"]
        for name, label in (("open_fragments", f"{c[str(scale['scene_counts'][-1])]['scenes']:,} fragments"),
                            ("open_compacted", "compacted (1 file)")):
            o = scale[name]
            lines.append(f"| {label} | {o['rows']:,} | {o['open_s']:.2f} | {o['peak_rss_mb']:.0f} | "
                         f"{o['token_lookup_ms']:.1f} | {o['identity_read_ms']:.1f} |")
        k, cl = scale["compact"], scale["clips_compacted"]
        lines += ["", f"Compaction of {k['files_before']:,} files into one ({k['rows']:,} rows, "
                  f"{k['bytes'] / 1e6:.0f} MB): {k['seconds']:.1f} s. `OccupancyDataset(clip_len=8, stride=4, "
                  f"subset='spatial')` index from columns: {cl['clips']:,} clips in {cl['index_s']:.2f} s, peak RSS "
                  f"{cl['peak_rss_mb']:.0f} MB ({cl['rss_after_torch_import_mb']:.0f} MB after the imports).", ""]
    w = report.get("work")
    if w:
        lines += [f"## Work folder per output frame (real build, {w['frames']} frames, default params)", "",
                  "| stage | cache bytes / frame |", "|---|---:|"]
        lines += [f"| {k} | {v / 1e3:,.0f} KB |" for k, v in w["stage_bytes_per_frame"].items()]
        lines += ["", "| --keep-work | work bytes / frame |", "|---|---:|"]
        lines += [f"| {k} | {v / 1e3:,.0f} KB |" for k, v in w["work_bytes_per_frame"].items()]
        lines += ["", f"The dataset itself (shards, manifest, metadata): {w['dataset_bytes_per_frame'] / 1e3:,.0f} KB per frame.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench"))
    parser.add_argument("--only", choices=["scale", "work"], default=None)
    parser.add_argument("--scenes", default=",".join(map(str, SCENE_COUNTS)),
                        help="Manifest sizes (scenes of 190 rows) of the commit points; the last one is opened.")
    parser.add_argument("--log-seconds", type=float, default=2.0, help="Synthetic log length of the work section.")
    args = parser.parse_args(argv)
    work = args.out / "manifest_work"
    work.mkdir(parents=True, exist_ok=True)
    path = args.out / "report-manifest.json"
    report = json.loads(path.read_text()) if path.exists() else {}
    report.update({"software": __version__, "machine": f"{platform.machine()}, {platform.python_version()}"})
    if args.only in (None, "scale"):
        report["scale"] = bench_commit_and_open(work, tuple(int(n) for n in args.scenes.split(",")))
    if args.only in (None, "work"):
        report["work"] = bench_work(work, args.log_seconds)
    path.write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    (args.out / "report-manifest.md").write_text(render_markdown(report))
    print(render_markdown(report))


if __name__ == "__main__":
    main()
