"""`make bench`: synthesize a fixed `small` log, build it (local and Ray, side by side), and measure the
build against the synthetic truth. Writes bench/report.json and bench/report.md.

Sections: build (wall time per stage, frames/s, per-frame cost per core, peak RSS, bytes per frame,
local vs Ray), quality (IoU / mIoU / per-class IoU in the truth's LiDAR mask, trails, ground holes,
side by side with the paper's method on the same surfaces), FBSA (pose error before and after
registration against the true poses), reconstruction (torch solver vs Poisson vs raw points against
a known surface), per-frame voxel costs, decode throughput, and optionally occgen training figures.
Figures are medians over frames; every comparison is measured in the same run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from nuplan_occ import __version__
from nuplan_occ.dataset import open_dataset
from nuplan_occ.evaluation.datasets import N_IDS, confusion, pooled_metrics
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.io.data_root import resolve_logs
from nuplan_occ.labels import LABELS, ROAD, ROAD_LINE
from nuplan_occ.pipeline.build import default_work_root, plan_tasks, run_build
from nuplan_occ.pipeline.params import default_params
from nuplan_occ.pipeline.runner import run_stages
from nuplan_occ.storage.digest import content_digests
from benchmarks.paper_method import paper_column_stamp, paper_voxelize_vertices
from nuplan_occ.map_labels.bev import rasterize_bev
from nuplan_occ.evaluation.grid_metrics import ground_hole_rate, occupancy_metrics, trail_count, unannotated_objects

BENCH_SEED = 0
TRAIL_GROUND_CLEARANCE_M = 0.3


def published_digest(root: Path) -> str:
    """sha256 over the published items (shards, visible manifest rows, metadata) of a dataset root."""
    digests = content_digests(str(root))
    return hashlib.sha256(json.dumps(digests, sort_keys=True).encode()).hexdigest()


def bench_build(data_root: Path, out_dir: Path, workers: int) -> dict[str, Any]:
    """Local and Ray builds of the same log from scratch; timings and identical-bytes check."""
    from nuplan_occ.stages import PIPELINE

    rows = {}
    for executor in ("local", "ray"):
        out = out_dir / f"build_{executor}"
        shutil.rmtree(out, ignore_errors=True)
        summary = run_build(data_root, str(out), default_params(PIPELINE), pipeline=PIPELINE, workers=workers, executor=executor)
        rows[executor] = {**summary.to_dict(), "frames_per_s": summary.frames_built / summary.wall_seconds,
                          "digest": published_digest(out)}
    local = rows["local"]
    cpu_seconds = sum(local["stage_seconds"].values())
    return {
        "workers": workers,
        "local": local,
        "ray": rows["ray"],
        "identical_bytes_local_vs_ray": rows["local"]["digest"] == rows["ray"]["digest"],
        "seconds_per_frame_per_core": cpu_seconds / max(local["frames_built"], 1),
        "stage_seconds_per_frame": {k: v / max(local["frames_built"], 1) for k, v in local["stage_seconds"].items()},
    }


def scene_artifacts(data_root: Path, out: Path) -> list[dict[str, Any]]:
    """The cached stage artifacts of every scene of the local build (nothing is recomputed)."""
    from nuplan_occ.stages import PIPELINE

    params = default_params(PIPELINE)
    tasks = plan_tasks(resolve_logs(data_root), data_root, data_root / "maps", str(out), default_work_root(str(out)), params)
    wanted = ("scene", "registration", "object_boxes", "background_surface", "scene_frame", "objects",
              "object_surfaces")
    return [run_stages(task, PIPELINE, wanted) for task in tasks]


def swept_mask(scene, pose: np.ndarray) -> np.ndarray:
    """Voxels that the boxes of moving agents cover at any sweep of the scene, in the ego grid of `pose`
    (T_global_from_ego), leaving out each box's lowest `TRAIL_GROUND_CLEARANCE_M` (where the road surface
    runs under it: a ground layer one voxel too thick is a ground error, measured by IoU, not a trail).
    Intersected with the truth's empty space, this is where a motion trail would show."""
    from nuplan_occ.pipeline.frame_columns import MOVING_SPEED_MPS
    from nuplan_occ.voxel.voxelize import box_voxel_indices, indices_to_grid

    T_ego_from_global = invert_transform(pose)
    mask = np.zeros(DEFAULT_GRID.shape, dtype=bool)
    for sweep in scene.sweeps:
        boxes = sweep.boxes_global.transformed(T_ego_from_global, "ego")
        moving = np.flatnonzero(np.linalg.norm(boxes.velocities[:, :2], axis=1) > MOVING_SPEED_MPS)
        for k in moving:
            center = boxes.centers[k] + [0.0, 0.0, TRAIL_GROUND_CLEARANCE_M / 2]
            size = boxes.sizes[k] - [0.0, 0.0, TRAIL_GROUND_CLEARANCE_M]
            mask |= indices_to_grid(box_voxel_indices(center, boxes.yaws[k], size, DEFAULT_GRID))
    return mask


def paper_method_frame(artifacts: dict, token: str, position: int, layers) -> np.ndarray:
    """The paper's voxelization and labeling on the same surfaces: background and object mesh vertices
    (one midpoint subdivision; objects posed by their box and cropped to it) with a majority label per
    voxel, then whole-column map stamping of background voxels."""
    from nuplan_occ.voxel.placement import placed_objects
    from nuplan_occ.geometry import yaw_matrix
    from nuplan_occ.voxel.voxelize import in_box

    scene, pose = artifacts["scene"], artifacts["registration"].poses[position]
    surface = artifacts["background_surface"]
    T = invert_transform(pose) @ artifacts["scene_frame"]
    vertices = [transform_points(T, surface.vertices)]
    labels = [np.full(len(surface.vertices), 1, dtype=np.uint8)]
    faces = [surface.faces]
    offset = len(surface.vertices)
    ok_position = {p: i for i, p in enumerate(scene.ok_indices())}
    objects = placed_objects(scene.instance_ids, artifacts["object_boxes"][position], ok_position[position],
                             artifacts["objects"], artifacts["object_surfaces"], {}, 2)  # the paper meshes objects: no carved solids
    for obj in objects:
        posed = obj.vertices @ yaw_matrix(obj.yaw).T + obj.center
        keep = in_box(posed, obj.center, obj.yaw, obj.size)
        vertices.append(posed[keep])
        labels.append(np.full(int(keep.sum()), obj.class_id, dtype=np.uint8))
        if len(obj.faces):
            remap = np.cumsum(keep) - 1
            kept_faces = obj.faces[keep[obj.faces].all(axis=1)]
            faces.append(remap[kept_faces] + offset)
        offset += int(keep.sum())
    semantics = paper_voxelize_vertices(np.concatenate(vertices), DEFAULT_GRID, faces=np.concatenate(faces),
                                        labels=np.concatenate(labels))
    if layers is None:
        return semantics
    bev = rasterize_bev(layers, pose, DEFAULT_GRID)
    return paper_column_stamp(semantics, np.isin(bev, [ROAD, ROAD_LINE]), bev == ROAD_LINE, DEFAULT_GRID)


def bench_quality(data_root: Path, out: Path, frame_stride: int = 1) -> dict[str, Any]:
    """Built frames (read from the dataset at `out`) vs truth inside the truth's mask_lidar; the paper's
    method on the same input. frame_stride: measure every n-th built frame of a scene."""
    from nuplan_occ.io.maps import LABEL_LAYERS, NuplanMap

    truth = open_dataset(str(data_root / "truth"))
    built = open_dataset(str(out))
    ours, paper, trails, paper_trails, holes, paper_holes = [], [], [], [], [], []
    ours_confusion, paper_confusion = np.zeros((N_IDS, N_IDS), np.int64), np.zeros((N_IDS, N_IDS), np.int64)
    ours_annotated, paper_annotated = np.zeros_like(ours_confusion), np.zeros_like(paper_confusion)
    for artifacts in scene_artifacts(data_root, out):
        scene = artifacts["scene"]
        layers = None
        if scene.map_path:
            center = artifacts["registration"].poses[0][:2, 3]
            layers = NuplanMap(scene.map_path).layers_in_window(center, 150.0, LABEL_LAYERS)
        position_of = {s.token: i for i, s in enumerate(scene.sweeps)}
        tokens = [s.token for s in scene.sweeps if s.is_output and s.has_cloud][::max(1, frame_stride)]
        for token in tokens:
            frame = built.get(built.index_of_token(token), keys=("semantics", "instance"))
            semantics, objects = frame["semantics"], frame["instance"] > 0
            reference = truth[truth.index_of_token(token)]
            mask = reference["mask_lidar"]
            baseline = paper_method_frame(artifacts, token, position_of[token], layers)
            ours.append(occupancy_metrics(semantics, reference["semantics"], mask))
            paper.append(occupancy_metrics(baseline, reference["semantics"], mask))
            ours_confusion += confusion(semantics, reference["semantics"], mask)
            paper_confusion += confusion(baseline, reference["semantics"], mask)
            boxes = artifacts["object_boxes"][position_of[token]]
            annotated = mask & ~unannotated_objects(reference["instance"], boxes.centers, boxes.yaws, boxes.sizes)
            ours_annotated += confusion(semantics, reference["semantics"], annotated)
            paper_annotated += confusion(baseline, reference["semantics"], annotated)
            swept = swept_mask(scene, artifacts["registration"].poses[position_of[token]])
            swept &= reference["semantics"] == 0  # truly empty now: anything built there is a trail
            trails.append(trail_count(semantics, swept, objects))
            paper_trails.append(trail_count(baseline, swept, objects))
            road = np.isin(reference["semantics"], [ROAD, ROAD_LINE])
            ground_index = np.argmax(road, axis=2)
            observed = np.take_along_axis(mask, ground_index[:, :, None], axis=2)[:, :, 0]
            drivable = road.any(axis=2) & observed  # drivable columns whose road voxel the sweep observed
            holes.append(ground_hole_rate(semantics, drivable, ground_index))
            paper_holes.append(ground_hole_rate(baseline, drivable, ground_index))
    return {
        "frames": len(ours),
        "ours": summarize_metrics(ours, trails, holes, ours_confusion, ours_annotated),
        "paper_method": summarize_metrics(paper, paper_trails, paper_holes, paper_confusion, paper_annotated),
    }


def summarize_metrics(metrics: list[dict], trails: list[int], holes: list[float], pooled_confusion: np.ndarray,
                      annotated_confusion: np.ndarray) -> dict[str, Any]:
    """Medians over frames of IoU, mIoU and per-class IoU; total trail voxels; median hole rate;
    "pooled": IoU, mIoU and per-class IoU of the confusion summed over the frames (as `nuplan-occ eval`
    and Occ3D-style benchmarks count: a class absent from most frames' truth weighs by its voxels); and
    "pooled_annotated": the same without the truth voxels of objects the log has no box for
    (`unannotated_objects`: the synthetic logs leave one moving object unboxed on purpose)."""
    classes = sorted({c for m in metrics for c in m["per_class"]})

    def pooled_figures(conf: np.ndarray) -> dict[str, Any]:
        pooled = pooled_metrics(conf, classes)
        return {"iou": pooled["iou"], "miou": pooled["miou"],
                "per_class_iou": {LABELS.names[c]: v for c, v in pooled["per_class"].items()}}

    return {
        "pooled": pooled_figures(pooled_confusion),
        "pooled_annotated": pooled_figures(annotated_confusion),
        "iou": float(np.median([m["iou"] for m in metrics])),
        "miou": float(np.median([m["miou"] for m in metrics])),
        "per_class_iou": {LABELS.names[c]: float(np.median([m["per_class"][c] for m in metrics if c in m["per_class"]]))
                          for c in classes},
        "trail_voxels_total": int(np.sum(trails)),
        "ground_hole_rate": float(np.median(holes)),
    }


def bench_fbsa(data_root: Path, out: Path) -> dict[str, Any]:
    """Pose error of logged, refined and map-aligned poses (refined, corrected by the scene's alignment of
    the map to the LiDAR's paint, as written to the manifest) against the true poses (synthetic truth), per
    sweep; runs only the stages up to the map alignment (cached by `out`'s work folder)."""
    from nuplan_occ.evaluation.step_metrics import pose_errors
    from nuplan_occ.stages import PIPELINE

    params = default_params(PIPELINE)
    tasks = plan_tasks(resolve_logs(data_root), data_root, data_root / "maps", str(out), default_work_root(str(out)), params)
    truth = open_dataset(str(data_root / "truth"))
    logged, refined, aligned, true, accepted = [], [], [], [], []
    for task in tasks:
        artifacts = run_stages(task, PIPELINE, ("scene", "registration", "map_alignment"))
        scene, registration, alignment = artifacts["scene"], artifacts["registration"], artifacts["map_alignment"]
        correction = alignment.correction if alignment is not None else np.eye(4)
        for position, sweep in enumerate(scene.sweeps):
            logged.append(sweep.logged_pose)
            refined.append(registration.poses[position])
            aligned.append(correction @ registration.poses[position])
            true.append(truth.get(truth.index_of_token(sweep.token), keys=())["ego_to_global"])
            accepted.append(bool(registration.accepted[position]))
    truth_poses = np.stack(true)
    return {
        "frames": len(true),
        "accepted_fraction": float(np.mean(accepted)),
        "logged": pose_errors(np.stack(logged), truth_poses).medians(),
        "refined": pose_errors(np.stack(refined), truth_poses).medians(),
        "map_aligned": pose_errors(np.stack(aligned), truth_poses).medians(),
    }


NOISY_LOG_OPTIONS = {"pose_noise_xy": 0.3, "pose_noise_yaw_deg": 1.0, "drift_z": 0.12}
"""The condition registration is held to: logged-pose noise 0.3 m / 1 deg plus a slow z drift."""


def bench_fbsa_noisy(out_dir: Path, seconds: float) -> dict[str, Any]:
    """bench_fbsa on a log synthesized with NOISY_LOG_OPTIONS' pose noise (same world and seed)."""
    from nuplan_occ.synth.generate import synthesize
    from nuplan_occ.synth.presets import SynthOptions

    data_root = out_dir / "data_noisy"
    shutil.rmtree(data_root, ignore_errors=True)
    synthesize(data_root, logs=1, seconds=seconds, seed=BENCH_SEED, preset="small",
               options=SynthOptions(**NOISY_LOG_OPTIONS))
    return {"options": NOISY_LOG_OPTIONS, **bench_fbsa(data_root, out_dir / "fbsa_noisy")}


def bench_recon(half_extent: float) -> list[dict]:
    """The three surface methods on a synthetic street scan, against its noise-free surface."""
    from benchmarks.recon_bench import compare_methods
    from nuplan_occ.synth.surface_scans import street_scan

    scan = street_scan(half=half_extent)
    return compare_methods(scan.points, scan.origins, scan.truth_points)


def bench_voxel_costs() -> dict[str, Any]:
    """Median seconds per frame of compose, LiDAR and camera visibility on a realistic frame."""
    from benchmarks.voxel_bench import synthetic_frame_costs

    return synthetic_frame_costs()


def bench_occgen(out_dir: Path, steps: int) -> dict[str, Any]:
    """occgen: VAE reconstruction at both compression ratios, and learned LiDAR vs ray casting."""
    from benchmarks.occgen_bench import make_synthetic_dataset, run_vae_bench, write_curve_png

    data = out_dir / "occgen_data"
    shutil.rmtree(data, ignore_errors=True)
    make_synthetic_dataset(str(data))
    results = {name: run_vae_bench(str(data), steps, config=name) for name in ("tiny", "tiny512")}
    write_curve_png({name: r["losses"] for name, r in results.items()}, out_dir / "occgen_vae_loss.png")
    return {name: {k: v for k, v in r.items() if k not in ("losses", "loss_terms")} for name, r in results.items()}


def write_report(report: dict, out_dir: Path) -> None:
    """bench/report.json and a readable bench/report.md."""
    (out_dir / "report.json").write_text(json.dumps(report, indent=2, default=float))
    (out_dir / "report.md").write_text(render_markdown(report))


def _table(header: list[str], rows: list[list[Any]]) -> str:
    def cell(value: Any) -> str:
        return f"{value:.4g}" if isinstance(value, float) else str(value)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def render_markdown(report: dict) -> str:
    """The report as Markdown tables."""
    parts = [f"# nuplan-occ bench ({report['software']}, {report['machine']})", "",
             f"Synthetic `small` log, seed {report['seed']}, {report['seconds']} s; targets in brackets.", ""]
    if "build" in report:
        b = report["build"]
        parts += ["## Build", "", _table(
            ["executor", "frames", "failed", "wall s", "frames/s", "bytes/frame", "peak RSS MiB"],
            [[name, b[name]["frames_built"], b[name]["frames_failed"], b[name]["wall_seconds"], b[name]["frames_per_s"],
              b[name]["bytes_per_frame"], b[name]["peak_rss_mb_per_worker"]] for name in ("local", "ray")]), "",
            f"- identical bytes local vs Ray: {b['identical_bytes_local_vs_ray']}",
            f"- seconds per frame per core (sum of stage times / frames): {b['seconds_per_frame_per_core']:.2f} [<= 1.0]",
            "", _table(["stage", "s per frame"], [[k, v] for k, v in b["stage_seconds_per_frame"].items()]), ""]
    if "quality" in report:
        q = report["quality"]
        classes = sorted(set(q["ours"]["per_class_iou"]) | set(q["paper_method"]["per_class_iou"]))
        parts += ["## Quality against truth (inside the truth's mask_lidar, median over frames)", "",
                  f"{q['frames']} frames. Targets: IoU >= 0.85, mIoU >= 0.75, zero trails.", "",
                  _table(["method", "IoU", "mIoU", "trail voxels", "ground hole rate", *classes],
                         [[name, q[name]["iou"], q[name]["miou"], q[name]["trail_voxels_total"], q[name]["ground_hole_rate"],
                           *[q[name]["per_class_iou"].get(c, float("nan")) for c in classes]]
                          for name in ("ours", "paper_method")]), ""]
        if "pooled" in q["ours"]:
            parts += ["Pooled over the frames (one confusion summed over every frame, as `nuplan-occ eval` counts):", "",
                      _table(["method", "IoU", "mIoU", *classes],
                             [[name, q[name]["pooled"]["iou"], q[name]["pooled"]["miou"],
                               *[q[name]["pooled"]["per_class_iou"].get(c, float("nan")) for c in classes]]
                              for name in ("ours", "paper_method")]), ""]
    for section, title in (("fbsa", "default synthetic log noise"), ("fbsa_noisy", "logged-pose noise 0.3 m / 1 deg + z drift")):
        if section not in report:
            continue
        f = report[section]
        keys = list(f["logged"])
        parts += [f"## Pose refinement, {title} (median absolute error against the true poses)", "",
                  f"{f['frames']} sweeps, {f['accepted_fraction']:.0%} corrections accepted. Targets: <= 5 cm, <= 0.1 deg.", "",
                  _table(["poses", *keys], [[name, *[f[name][k] for k in keys]] for name in ("logged", "refined", "map_aligned") if name in f]), ""]
    if "recon" in report:
        keys = ["time_s", "peak_mb", "chamfer", "precision@0.1", "recall@0.1", "fscore@0.1", "precision@0.25",
                "recall@0.25", "fscore@0.25"]
        rows = [[r["method"], *[r.get(k, float("nan")) for k in keys]] for r in report["recon"]]
        parts += ["## Surface reconstruction (synthetic street scan vs its noise-free surface)", "",
                  _table(["method", *keys], rows), ""]
    if "voxel_costs" in report:
        parts += ["## Per-frame voxel work (median s)", "",
                  _table(["step", "s"], [[k, v] for k, v in report["voxel_costs"].items() if isinstance(v, float)]), ""]
    if "decode" in report:
        parts += ["## Decode", "", _table(["what", "value"], [[k, v] for k, v in report["decode"].items()]), ""]
    if "occgen" in report:
        parts += ["## occgen VAE (short CPU training)", "",
                  _table(["config", "steps", "compression", "IoU", "mIoU"],
                         [[n, r["steps"], r["compression_ratio"], r["iou"], r["miou"]] for n, r in report["occgen"].items()]), ""]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=["bench"])
    parser.add_argument("--out", type=Path, default=Path("bench"))
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--recon-extent", type=float, default=30.0, help="half extent (m) of the recon bench street")
    parser.add_argument("--occgen-steps", type=int, default=0, help="occgen VAE training steps (0 = skip)")
    args = parser.parse_args(argv)

    from benchmarks.throughput import decode_throughput
    from nuplan_occ.synth.generate import synthesize

    args.out.mkdir(parents=True, exist_ok=True)
    data_root = args.out / "data"
    shutil.rmtree(data_root, ignore_errors=True)
    started = time.perf_counter()
    synthesize(data_root, logs=1, seconds=args.seconds, seed=BENCH_SEED, preset="small")
    report: dict[str, Any] = {"software": f"nuplan-occ {__version__}", "machine": platform.machine(),
                              "seed": BENCH_SEED, "seconds": args.seconds,
                              "synth_seconds": time.perf_counter() - started}
    sections = [
        ("build", lambda: bench_build(data_root, args.out, args.workers)),
        ("quality", lambda: bench_quality(data_root, args.out / "build_local")),
        ("fbsa", lambda: bench_fbsa(data_root, args.out / "build_local")),
        ("fbsa_noisy", lambda: bench_fbsa_noisy(args.out, args.seconds)),
        ("recon", lambda: bench_recon(args.recon_extent)),
        ("voxel_costs", bench_voxel_costs),
        ("decode", lambda: decode_throughput(str(args.out / "build_local"))),
    ]
    if args.occgen_steps:
        sections.append(("occgen", lambda: bench_occgen(args.out, args.occgen_steps)))
    for name, run in sections:
        print(f"bench: {name} ...", flush=True)
        report[name] = run()
        write_report(report, args.out)
    print((args.out / "report.md").read_text())


if __name__ == "__main__":
    main()
