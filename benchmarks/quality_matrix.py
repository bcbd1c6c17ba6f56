"""`make bench-quality`: the quality matrix. Synthetic worlds the defaults were not tuned on,
imperfect logs and another road layout, each built from scratch by one worker and scored against its exact truth.

Worlds (20 s each by default, one scene spanning the log, truth every 10th sweep): `city` at the tuning seeds
(defaults may be tuned on these only) and at held-out seeds, the `realistic` imperfection profile on one tuning
and one held-out seed, `small_objects`, and the `suburb` layout at another location. Per world (figures pooled
over the evaluated frames; definitions in `DEFINITIONS`, repeated in the report): pooled occupied IoU, mIoU,
per-class IoU / precision / recall, trail, floater, below-ground and inside-ego voxel counts, and the build's
CPU seconds per frame. The report leads with the worst world per class.

Each world's result is kept under bench/quality/results/ (keyed by world, length and code), so the matrix can be
run world by world (--worlds) and a run of another code version (--source REV: built by the code of git revision
REV, exported next to the data) stands beside this code's in the report. Writes bench/report-quality.json and
bench/report-quality.md; synthesized logs are cached under bench/quality/data/.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from benchmarks.scale import code_label, export_revision, timed_build
from benchmarks.small import TRAIL_GROUND_CLEARANCE_M, _table
from nuplan_occ.dataset import open_dataset
from nuplan_occ.evaluation.datasets import N_IDS, confusion, pooled_metrics, write_json
from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.io.types import PACIFICA
from nuplan_occ.labels import EMPTY, GENERIC_OBJECT, LABELS, VEHICLE
from nuplan_occ.voxel.voxelize import box_voxel_indices, in_box

TRUTH_RATE_HZ = 2.0
"""Truth frames per second of the matrix's logs (every 10th sweep: 40 evaluated frames per 20 s world)."""
FLOATER_CLEARANCE_VOXELS = 4
"""A floater is more than this many voxels (1 m, Chebyshev) from every truth-occupied voxel."""
BELOW_GROUND_VOXELS = 2
"""Below ground: a voxel lying entirely more than 0.5 m (2 voxels) below its column's lowest truth voxel."""
MOVING_MPS = 0.5
"""An agent sweeps a trail volume when its true speed exceeds this."""
LIMIT_MB = 6000.0

DEFINITIONS = {
    "iou": "occupied-vs-empty IoU of the confusion matrix summed over the evaluated frames, inside the truth's mask_lidar",
    "miou": "mean of the per-class IoU over the classes with truth voxels in the world (pooled the same way)",
    "precision / recall": "per class c, pooled inside mask_lidar: voxels built c that are c in the truth / voxels built c "
                          "(precision), / truth voxels of c (recall)",
    "trail": "built occupied voxels (whole grid) that are empty in the truth, that a moving agent's TRUE box (its lowest "
             f"{TRAIL_GROUND_CLEARANCE_M} m left out) covers at some 10 Hz time of the scene, and that no agent's true box "
             "covers now (grown by one voxel): ghosts of moving objects, summed over the evaluated frames",
    "floater": f"built occupied voxels (whole grid) more than {FLOATER_CLEARANCE_VOXELS} voxels (Chebyshev) from every "
               "truth-occupied voxel, not below ground and not inside the ego; summed, and as a share of built occupied voxels",
    "below_ground": f"built occupied voxels lying entirely more than {BELOW_GROUND_VOXELS * 0.25} m below the bottom of the "
                    "lowest truth-occupied voxel of their column (the ground), summed over the evaluated frames",
    "inside_ego": "built occupied voxels whose centre lies inside the ego vehicle's box (PACIFICA, ego frame), summed",
    "unboxed movers": "built voxels of an object class (vehicle .. generic_object) without an instance id (the unboxed-"
                      "mover rule's), inside mask_lidar: their count per class and the share whose truth is that class",
}


@dataclass(frozen=True)
class MatrixWorld:
    """One world of the matrix: synth preset, seed, role ("tuning": defaults may be tuned on it; "held-out":
    never), imperfection profile (synth.presets.IMPERFECTIONS) and nuPlan location."""

    name: str
    preset: str
    seed: int
    role: str
    imperfections: str = "none"
    location: str = "us-nv-las-vegas-strip"


WORLDS = (
    MatrixWorld("city-s0", "city", 0, "tuning"),
    MatrixWorld("city-s1", "city", 1, "tuning"),
    MatrixWorld("city-s2", "city", 2, "tuning"),
    MatrixWorld("city-s7", "city", 7, "held-out"),
    MatrixWorld("city-s8", "city", 8, "held-out"),
    MatrixWorld("city-s9", "city", 9, "held-out"),
    MatrixWorld("small_objects-s0", "small_objects", 0, "held-out"),
    MatrixWorld("suburb-s0", "suburb", 0, "held-out", location="us-pa-pittsburgh-hazelwood"),
    MatrixWorld("city-s1-realistic", "city", 1, "tuning", "realistic"),
    MatrixWorld("city-s8-realistic", "city", 8, "held-out", "realistic"),
)


def world_data(cache: Path, world: MatrixWorld, seconds: float) -> Path:
    """The synthesized log of `world` (one scene of `seconds`, truth at TRUTH_RATE_HZ, no images, no camera
    mask), made under `cache` once per synth recipe (a changed recipe makes it again)."""
    from nuplan_occ.synth.generate import synthesize
    from nuplan_occ.synth.presets import imperfect_options

    options = imperfect_options(world.imperfections)
    recipe = json.dumps({**asdict(world), "seconds": seconds, "options": asdict(options)}, sort_keys=True)
    root = cache / f"{world.name}_{seconds:g}s"
    done = root / ".complete"
    if not done.exists() or done.read_text() != recipe:
        import shutil

        shutil.rmtree(root, ignore_errors=True)
        synthesize(root, logs=1, seconds=seconds, seed=world.seed, preset=world.preset, options=options,
                   truth_rate_hz=TRUTH_RATE_HZ, location=world.location, scene_seconds=seconds, camera_rate_hz=0.0,
                   camera_mask=False)
        done.write_text(recipe)
    return root


def true_boxes(world: MatrixWorld, seconds: float, times_us: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """TRUE boxes of every agent of the world's log at absolute times (T,) us: centres (T, A, 3) global m,
    yaws (T, A), sizes (A, 3), speeds (T, A) m/s."""
    from nuplan_occ.synth.logbuild import log_start
    from nuplan_occ.synth.presets import get_preset, imperfect_options
    from nuplan_occ.synth.world import build_world

    start_us = int(log_start(world.seed, 0).timestamp()) * 1_000_000
    synth_world = build_world(get_preset(world.preset), imperfect_options(world.imperfections), world.seed, 0, seconds,
                              start_us, world.location)
    t = (np.asarray(times_us, np.int64) - start_us) / 1e6
    states = [agent.state(t) for agent in synth_world.agents]
    centers = np.stack([s[0] for s in states], axis=1) + synth_world.origin
    yaws = np.stack([s[1] for s in states], axis=1)
    speeds = np.stack([np.linalg.norm(s[2][:, :2], axis=1) for s in states], axis=1)
    return centers, yaws, np.stack([a.size for a in synth_world.agents]), speeds


def _ego_box_mask() -> np.ndarray:
    center, size = PACIFICA.box_center_and_size()
    return np.asarray(in_box(DEFAULT_GRID.voxel_centers().reshape(-1, 3), center, 0.0, size)).reshape(DEFAULT_GRID.shape)


def _boxes_mask(centers: np.ndarray, yaws: np.ndarray, sizes: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
    mask = np.zeros(DEFAULT_GRID.shape, dtype=bool)
    reach = 75.0
    for center, yaw, size in zip(centers, yaws, sizes):
        if np.linalg.norm(center[:2]) > reach:
            continue
        index = box_voxel_indices(center, float(yaw), size, DEFAULT_GRID, margin_m)
        mask[index[:, 0], index[:, 1], index[:, 2]] = True
    return mask


def _to_ego(T_ego_from_global: np.ndarray, centers: np.ndarray, yaws: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, p = T_ego_from_global[:3, :3], T_ego_from_global[:3, 3]
    return centers @ R.T + p, yaws + np.arctan2(R[1, 0], R[0, 0])


def below_ground_mask(truth_semantics: np.ndarray) -> np.ndarray:
    """bool (X, Y, Z): voxels entirely more than BELOW_GROUND_VOXELS voxels below the lowest truth-occupied voxel
    of their column (columns without any truth voxel: none)."""
    occupied = truth_semantics != EMPTY
    lowest = np.where(occupied.any(axis=2), np.argmax(occupied, axis=2), -1)
    z = np.arange(truth_semantics.shape[2])
    return z[None, None, :] < (lowest[:, :, None] - BELOW_GROUND_VOXELS)


def evaluate_world(world: MatrixWorld, seconds: float, data_root: Path, built_root: Path) -> dict[str, Any]:
    """The matrix figures (see DEFINITIONS) of the build at built_root against the truth under data_root."""
    truth = open_dataset(str(data_root / "truth"))
    built = open_dataset(str(built_root))
    built_tokens = set(built.manifest["token"].to_pylist())
    matched = [j for j, token in enumerate(truth.manifest["token"].to_pylist()) if token in built_tokens]
    sweep_us = np.asarray(sorted(built.manifest["timestamp_us"].to_pylist()), np.int64) if "timestamp_us" in \
        built.manifest.column_names else None
    truth_us = [int(truth.get(j, keys=())["timestamp_us"]) for j in matched]
    times_us = sweep_us if sweep_us is not None else np.asarray(truth_us, np.int64)
    centers, yaws, sizes, speeds = true_boxes(world, seconds, times_us)
    now_centers, now_yaws, _, _ = true_boxes(world, seconds, np.asarray(truth_us, np.int64))
    ego_box = _ego_box_mask()
    total = np.zeros((N_IDS, N_IDS), np.int64)
    unboxed = np.zeros((N_IDS, N_IDS), np.int64)
    counts = {"trail": 0, "floater": 0, "below_ground": 0, "inside_ego": 0, "occupied": 0}
    moving = speeds > MOVING_MPS
    for n, j in enumerate(matched):
        reference = truth.get(j, keys=("semantics", "mask_lidar"))
        frame = built.get(built.index_of_token(reference["token"]), keys=("semantics", "instance"))
        pred, truth_sem = frame["semantics"], reference["semantics"]
        total += confusion(pred, truth_sem, reference["mask_lidar"])
        unboxed += confusion(pred, truth_sem, reference["mask_lidar"] & (frame["instance"] == 0) & (pred >= VEHICLE)
                             & (pred <= GENERIC_OBJECT))
        T = invert_transform(reference["ego_to_global"])
        built_occ = pred != EMPTY
        c_now, y_now = _to_ego(T, now_centers[n], now_yaws[n])
        current = _boxes_mask(c_now, y_now, sizes, margin_m=DEFAULT_GRID.voxel_size)
        swept = np.zeros(DEFAULT_GRID.shape, dtype=bool)
        lift = np.array([0.0, 0.0, TRAIL_GROUND_CLEARANCE_M / 2])
        for k in range(len(times_us)):
            agents = np.flatnonzero(moving[k])
            if len(agents):
                c, y = _to_ego(T, centers[k, agents], yaws[k, agents])
                swept |= _boxes_mask(c + lift, y, sizes[agents] - [0.0, 0.0, TRAIL_GROUND_CLEARANCE_M])
        below = below_ground_mask(truth_sem)
        near_truth = ndimage.maximum_filter(truth_sem != EMPTY, size=2 * FLOATER_CLEARANCE_VOXELS + 1)
        counts["trail"] += int(np.count_nonzero(built_occ & swept & (truth_sem == EMPTY) & ~current))
        counts["floater"] += int(np.count_nonzero(built_occ & ~near_truth & ~below & ~ego_box))
        counts["below_ground"] += int(np.count_nonzero(built_occ & below))
        counts["inside_ego"] += int(np.count_nonzero(built_occ & ego_box))
        counts["occupied"] += int(np.count_nonzero(built_occ))
    classes = sorted(c for c in LABELS.names if c != EMPTY and (total[c, :].sum() or total[:, c].sum()))
    pooled = pooled_metrics(total, classes)
    per_class = {}
    for c in classes:
        truth_n, pred_n, hit = int(total[c, :].sum()), int(total[:, c].sum()), int(total[c, c])
        per_class[LABELS.names[c]] = {"iou": pooled["per_class"][c], "precision": hit / pred_n if pred_n else float("nan"),
                                      "recall": hit / truth_n if truth_n else float("nan"),
                                      "truth_voxels": truth_n, "built_voxels": pred_n}
    movers = {LABELS.names[c]: {"voxels": int(unboxed[:, c].sum()), "precision": float(unboxed[c, c] / unboxed[:, c].sum())}
              for c in range(VEHICLE, GENERIC_OBJECT + 1) if unboxed[:, c].sum()}
    return {"frames": len(matched), "iou": pooled["iou"], "miou": pooled["miou"], "per_class": per_class,
            "unboxed_movers": movers,
            "trail_voxels": counts["trail"], "floater_voxels": counts["floater"],
            "floater_share": counts["floater"] / max(counts["occupied"], 1), "below_ground_voxels": counts["below_ground"],
            "inside_ego_voxels": counts["inside_ego"], "occupied_voxels": counts["occupied"]}


def run_world(world: MatrixWorld, seconds: float, cache: Path, code: str, source: Path) -> dict[str, Any]:
    """Synthesize (cached), build from scratch with the code under `source`, evaluate; the world's result."""
    data_root = world_data(cache / "data", world, seconds)
    out = cache / "build" / f"{world.name}_{seconds:g}s_{code}"
    print(f"bench-quality: {world.name} ({seconds:g} s), code {code}: building ...", flush=True)
    build = timed_build(data_root, out, source, LIMIT_MB)
    result: dict[str, Any] = {"world": asdict(world), "seconds": seconds, "code": code,
                              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                              "build": {k: build[k] for k in ("ok", "killed", "frames_built", "frames_failed",
                                                              "cpu_seconds_per_frame", "stage_cpu_seconds_per_frame",
                                                              "peak_rss_mb")}}
    if build["ok"]:
        print(f"bench-quality: {world.name}: evaluating ...", flush=True)
        result["quality"] = evaluate_world(world, seconds, data_root, out)
    return result


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def worst_per_class(results: list[dict]) -> list[list[str]]:
    """Rows [class, worst world, IoU, precision, recall, truth voxels, mean IoU over worlds] for every class
    with truth voxels in some world, worst = lowest IoU among the worlds where the class has truth voxels."""
    scored = [r for r in results if "quality" in r]
    names = sorted({c for r in scored for c, v in r["quality"]["per_class"].items() if v["truth_voxels"]})
    rows = []
    for name in names:
        having = [r for r in scored if r["quality"]["per_class"].get(name, {}).get("truth_voxels", 0)]
        worst = min(having, key=lambda r: r["quality"]["per_class"][name]["iou"])
        figures = worst["quality"]["per_class"][name]
        mean = float(np.mean([r["quality"]["per_class"][name]["iou"] for r in having]))
        rows.append([name, worst["world"]["name"], _fmt(figures["iou"]), _fmt(figures["precision"]),
                     _fmt(figures["recall"]), str(figures["truth_voxels"]), _fmt(mean)])
    return rows


def compared(before: list[dict], after: list[dict], old: str, new: str) -> list[str]:
    """Markdown lines: the worlds scored by both codes, their headline figures side by side (old -> new)."""
    by_name = {r["world"]["name"]: r for r in before if "quality" in r}
    rows = []
    for r in after:
        if "quality" not in r or r["world"]["name"] not in by_name:
            continue
        a, b = by_name[r["world"]["name"]]["quality"], r["quality"]
        cpu = (by_name[r["world"]["name"]]["build"]["cpu_seconds_per_frame"], r["build"]["cpu_seconds_per_frame"])
        worst = min(b["per_class"], key=lambda c: b["per_class"][c]["iou"] if b["per_class"][c]["truth_voxels"] else 9)
        rows.append([r["world"]["name"], r["world"]["role"]] + [f"{_fmt(a[k])} -> {_fmt(b[k])}" for k in ("iou", "miou")]
                    + [f"{_fmt(a['per_class'].get('vehicle', {}).get('iou'))} -> {_fmt(b['per_class'].get('vehicle', {}).get('iou'))}",
                       f"{worst} {_fmt(b['per_class'][worst]['iou'])}"]
                    + [f"{a[k]} -> {b[k]}" for k in ("trail_voxels", "floater_voxels", "below_ground_voxels", "inside_ego_voxels")]
                    + [f"{_fmt(cpu[0])} -> {_fmt(cpu[1])}"])
    if not rows:
        return []
    return [f"## Before / after: code {old} -> {new}", "",
            _table(["world", "role", "IoU", "mIoU", "vehicle IoU", f"worst class ({new})", "trail", "floater", "below ground",
                    "inside ego", "CPU s/frame"], rows), ""]


def render_markdown(report: dict) -> str:
    """The matrix report: worst world per class first (per code, newest first), then per-world tables."""
    lines = ["# Quality matrix (`make bench-quality`)", "",
             f"Worlds of {report['seconds']:g} s, one scene each, built from scratch by one worker; scored against the "
             "exact synthetic truth (definitions at the end). Roles: *tuning* worlds may be used to tune defaults, "
             "*held-out* ones never.", ""]
    codes = list(report["runs"])
    for code in reversed(codes):
        results = report["runs"][code]
        names = ", ".join(r["world"]["name"] for r in results if "quality" in r)
        lines += [f"## Worst world per class: code {code}", "", f"Over {len(results)} worlds: {names}.", "",
                  _table(["class", "worst world", "IoU", "precision", "recall", "truth voxels", "mean IoU (worlds)"],
                         worst_per_class(results)), ""]
    if len(codes) > 1:
        lines += compared(report["runs"][codes[0]], report["runs"][codes[-1]], codes[0], codes[-1])
    for code in reversed(codes):
        results = report["runs"][code]
        lines += [f"## Worlds: code {code}", ""]
        rows = []
        for r in results:
            q, b, w = r.get("quality", {}), r["build"], r["world"]
            rows.append([w["name"], w["role"], w["imperfections"], str(q.get("frames", 0)), _fmt(q.get("iou")),
                         _fmt(q.get("miou")), str(q.get("trail_voxels", "-")),
                         f"{q.get('floater_voxels', '-')} ({100 * q.get('floater_share', float('nan')):.3f} %)",
                         str(q.get("below_ground_voxels", "-")), str(q.get("inside_ego_voxels", "-")),
                         ", ".join(f"{c} {_fmt(m['precision'], 2)} ({m['voxels']})"
                                   for c, m in q.get("unboxed_movers", {}).items()) or "-",
                         _fmt(b["cpu_seconds_per_frame"]), b["killed"] or ("ok" if b["ok"] else "failed")])
        lines += [_table(["world", "role", "imperfections", "frames", "IoU", "mIoU", "trail", "floater", "below ground",
                          "inside ego", "unboxed movers: precision (voxels)", "CPU s/frame", "build"], rows), ""]
        names = sorted({c for r in results if "quality" in r for c in r["quality"]["per_class"]})
        for figure in ("iou", "precision", "recall"):
            table = [[r["world"]["name"]] + [_fmt(r["quality"]["per_class"].get(c, {}).get(figure)) for c in names]
                     for r in results if "quality" in r]
            lines += [f"Per-class {figure} (code {code}):", "", _table(["world"] + names, table), ""]
    lines += ["## Definitions", ""] + [f"- **{k}**: {v}." for k, v in DEFINITIONS.items()]
    lines += ["", "Trail, floater, below-ground and inside-ego counts are summed over the evaluated frames (truth every "
              f"{20 / TRUTH_RATE_HZ:g}th sweep). CPU s/frame is the build child's process time; worlds built while other "
              "jobs share the machine run slower, so compare it only between builds run together (the scale bench "
              "is the cost yardstick).", ""]
    return "\n".join(lines)


def write_report(out_dir: Path, seconds: float) -> dict:
    """bench/report-quality.{json,md} from every kept world result of `seconds` (grouped by code, in WORLDS order)."""
    results = [json.loads(p.read_text()) for p in sorted((out_dir / "quality" / "results").glob("*.json"))]
    order = {w.name: i for i, w in enumerate(WORLDS)}
    runs: dict[str, list] = {}
    for r in sorted(results, key=lambda r: (r["date"], order.get(r["world"]["name"], 99))):
        if r["seconds"] == seconds:
            runs.setdefault(r["code"], []).append(r)
    for code in runs:
        runs[code].sort(key=lambda r: order.get(r["world"]["name"], 99))
    report = {"seconds": seconds, "truth_rate_hz": TRUTH_RATE_HZ, "definitions": DEFINITIONS, "runs": runs}
    write_json(report, out_dir / "report-quality.json")
    (out_dir / "report-quality.md").write_text(render_markdown(report))
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench"))
    parser.add_argument("--seconds", type=float, default=20.0, help="Length of every world (20 s for the report).")
    parser.add_argument("--worlds", default="", help="Comma-separated world names (default: all).")
    parser.add_argument("--source", default=None, help="Build with the code of this git revision (or of this folder holding "
                        "a nuplan_occ package, labelled by its name) instead of this tree.")
    parser.add_argument("--report-only", action="store_true", help="Only rewrite the report from kept results.")
    parser.add_argument("--evaluate-only", action="store_true", help="Score the kept builds again (no synthesis, no "
                        "build): for figures added after a run.")
    args = parser.parse_args()
    cache = args.out.resolve() / "quality"
    chosen = [w for w in WORLDS if not args.worlds or w.name in args.worlds.split(",")]
    here = Path(__file__).resolve().parents[1]
    if args.source and Path(args.source).is_dir():
        code, source = Path(args.source).name, Path(args.source).resolve()
    elif args.source:
        code, source = args.source, export_revision(args.source, cache / "src")
    else:
        code, source = code_label(here), here
    if args.evaluate_only:
        for world in chosen:
            path = cache / "results" / f"{world.name}_{args.seconds:g}s_{code}.json"
            if path.exists():
                result = json.loads(path.read_text())
                out = cache / "build" / f"{world.name}_{args.seconds:g}s_{code}"
                if result["build"]["ok"]:
                    data_root = cache / "data" / f"{world.name}_{args.seconds:g}s"
                    result["quality"] = evaluate_world(world, args.seconds, data_root, out)
                    write_json(result, path)
    elif not args.report_only:
        (cache / "results").mkdir(parents=True, exist_ok=True)
        for world in chosen:
            result = run_world(world, args.seconds, cache, code, source)
            write_json(result, cache / "results" / f"{world.name}_{args.seconds:g}s_{code}.json")
            write_report(args.out, args.seconds)
    write_report(args.out, args.seconds)


if __name__ == "__main__":
    main()
