"""Scale bench of the build report: what a rerun costs when no scene changed, on simulated manifests of many
scenes (no shard is read: unchanged scenes are not rendered). Measures, per scene count: flag rules,
scene summaries, the content keys of every scene, and writing the paginated scene table, the gallery and
the index page; plus the size of the index page.

    python -m benchmarks.report_bench --scenes 1000 19000 --frames 190 --out bench/build-report-scale.md
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from nuplan_occ.report.flags import evaluate_rules
from nuplan_occ.report.frames import BuildFrames
from nuplan_occ.report.scenes import summarize_scenes
from nuplan_occ.report.writer import _index_page, _write_gallery, _write_scene_tables


def simulated_frames(scenes: int, frames_per_scene: int, seed: int = 0) -> BuildFrames:
    """A build of `scenes` scenes of `frames_per_scene` frames with plausible QA figures and 0.5 % failed frames."""
    rng = np.random.default_rng(seed)
    n = scenes * frames_per_scene
    scene = np.repeat(np.arange(scenes), frames_per_scene)
    ok = rng.random(n) > 0.005
    strings = lambda fmt, values: np.array([fmt.format(v) for v in values], dtype=object)  # noqa: E731
    columns = {
        "log": strings("log-{:05d}", scene // 20), "scene_token": strings("{:016x}", scene),
        "scene_name": strings("scene-{:04d}", scene % 20), "frame_index": np.tile(np.arange(frames_per_scene) * 2.0, scenes),
        "token": strings("{:016x}", np.arange(n) + 10**12), "timestamp_us": np.arange(n) * 1e5,
        "status": np.where(ok, "ok", "failed").astype(object),
        "failure_reason": np.where(ok, "", "/data/x.pcd: truncated PCD: 99 points need 1188 bytes").astype(object),
        "qa_pose_correction_m": np.abs(rng.normal(0.05, 0.1, n)), "qa_pose_accepted": rng.random(n) > 0.001,
        "qa_map_status": np.full(n, "", dtype=object), "qa_map_aligned": np.repeat(rng.random(scenes) > 0.02, frames_per_scene),
        "qa_map_offset_m": np.repeat(rng.random(scenes) * 0.3, frames_per_scene),
        "qa_map_yaw_deg": np.repeat(rng.normal(0, 0.1, scenes), frames_per_scene),
        "qa_lidar_observed_fraction": rng.normal(0.24, 0.03, n), "qa_point_coverage": rng.normal(0.99, 0.01, n),
        "qa_occupied_voxels": rng.normal(130000, 5000, n), "qa_boxes_with_points": rng.integers(0, 30, n).astype(float),
        "nbytes": rng.normal(125000, 5000, n),
    }
    columns["qa_boxes_labeled"] = columns["qa_boxes_with_points"] - (rng.random(n) < 0.002)
    for name in columns:
        if name.startswith("qa_") and columns[name].dtype == np.float64:
            columns[name][~ok] = np.nan
    poses = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    class_hist = rng.integers(0, 10**5, (n, 15))
    starts = np.arange(scenes) * frames_per_scene
    return BuildFrames(columns, poses, class_hist, ok, list(zip(starts.tolist(), (starts + frames_per_scene).tolist())))


def measure(scenes: int, frames_per_scene: int) -> dict:
    """Seconds of each step of an unchanged rerun over a simulated build, and the index page's bytes."""
    frames = simulated_frames(scenes, frames_per_scene)
    times = {}
    started = time.perf_counter()
    flags = evaluate_rules(frames.columns, frames.ok)
    times["flag rules"] = time.perf_counter() - started
    started = time.perf_counter()
    summaries = summarize_scenes(frames, flags, {})
    times["scene summaries"] = time.perf_counter() - started
    started = time.perf_counter()
    for s in summaries:
        frames.scene_key(s.start, s.stop)
    times["scene content keys"] = time.perf_counter() - started
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        started = time.perf_counter()
        _write_scene_tables(out, summaries, flags)
        _write_gallery(out, [])
        index = _index_page("simulated", {"params": {}}, frames, flags, summaries, [], int(flags.flagged.sum()))
        (out / "index.html").write_text(index)
        times["index, scene table, gallery pages"] = time.perf_counter() - started
        pages = len(list(out.glob("scenes-*.html")))
    return {"scenes": scenes, "frames": len(frames), "seconds": times, "index_kib": len(index.encode()) / 1024,
            "scene_table_pages": pages, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, nargs="+", default=[1000, 19000])
    parser.add_argument("--frames", type=int, default=190)
    parser.add_argument("--out", type=Path, default=Path("bench/build-report-scale.md"))
    args = parser.parse_args()
    results = [measure(s, args.frames) for s in args.scenes]
    steps = list(results[0]["seconds"])
    lines = ["# Build report at scale (unchanged rerun, simulated manifests)", "",
             "`python -m benchmarks.report_bench` (see its docstring). Seconds per step; the manifest read and the",
             "rendering of changed scenes come on top.", "",
             "| scenes | frames | " + " | ".join(steps) + " | index page KiB | table pages | peak RSS MiB |",
             "|" + "---|" * (len(steps) + 5)]
    for r in results:
        lines.append(f"| {r['scenes']:,} | {r['frames']:,} | " + " | ".join(f"{r['seconds'][s]:.2f}" for s in steps)
                     + f" | {r['index_kib']:.0f} | {r['scene_table_pages']} | {r['peak_rss_mib']:.0f} |")
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
