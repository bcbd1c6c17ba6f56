"""`python -m benchmarks.ray_consistency`: is ray consistency (`nuplan-occ qa`) a quality measure?

On synthetic `city` worlds with exact truth (one 5 s scene each, several seeds), each built with the default
params, every output frame's grid is degraded by one known damage of a random magnitude (or left as built):
    none      the built grid as it is;
    floaters  1 - 12 boxes of `other` voxels (0.5 - 2.5 m wide, 1 - 3 voxels thick), their bottom at ego z
              -0.25 to 1.5 m (the synthetic road lies at z -0.5 to -0.25 m), in empty space 4 - 35 m away;
    wall_gap  every occupied voxel from ego z = 0 m up (0.25 m above the road: walls, poles, trees, cars)
              removed in an azimuth wedge of 10 - 120 deg seen from the ego;
    drop      a share of 5 - 50 % of the occupied voxels removed at random;
    shift     the grid moved by 1 - 6 voxels along x and y (a pose error);
    trail     every vehicle voxel copied 1 - 16 voxels backwards along x (a moving car's smear);
    ghost     the ground voxels (road, other_ground, road_line) of a random half-plane copied 1 - 2 m up.
Each frame then gets its true IoU (occupied vs empty, inside the truth's mask_lidar, as `nuplan-occ eval`
counts it) and mIoU, and its truth-free ray figures from the sweep `nuplan-occ qa` picks (the code path
of `nuplan_occ.evaluation.ray_qa.score_scene`, refined poses from the build's work folder). Reported:
Spearman rank correlation across the frames of all worlds between each ray figure and the true IoU (target
|rho| >= 0.7), the same per damage kind, the figures of the exact truth grids themselves (the floor of a
perfect grid), and for every flag rule of ray_qa the true IoU of the frames it catches against the rest.

Writes bench/report-ray-consistency.json and .md. Worlds and builds are cached under --cache.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

from nuplan_occ.dataset import open_dataset
from nuplan_occ.evaluation.grid_metrics import occupancy_metrics
from nuplan_occ.evaluation.ray_qa import qa_dataset, scene_frames, scene_poses, scene_tasks, score_scene
from nuplan_occ.rays.frame_qa import FIGURES, frame_flags, frame_ray_columns, scoring_sweep
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import EMPTY, OTHER, VEHICLE
from nuplan_occ.rays.consistency import FLAG_RULES, GROUND_IDS
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.pipeline.params import default_params

PRESET = "city"
KINDS = ("none", "floaters", "wall_gap", "drop", "shift", "trail", "ghost")


def world(cache: Path, seed: int, seconds: float) -> tuple[Path, Path]:
    """(data root, built dataset) of the `city` world of `seed`: one scene of `seconds`, truth at 10 Hz, built
    with the default params by one worker; made once under `cache`."""
    from nuplan_occ.stages import PIPELINE
    from nuplan_occ.synth.generate import synthesize

    root, out = cache / f"{PRESET}_{seed}_{seconds:g}s", cache / f"{PRESET}_{seed}_{seconds:g}s_build"
    if not (root / ".complete").exists():
        shutil.rmtree(root, ignore_errors=True)
        synthesize(root, logs=1, seconds=seconds, seed=seed, preset=PRESET, scene_seconds=seconds, truth_rate_hz=10.0)
        (root / ".complete").touch()
    if not (out / ".complete").exists():
        shutil.rmtree(out, ignore_errors=True)
        run_build(root, str(out), default_params(PIPELINE), pipeline=PIPELINE, workers=1)
        (out / ".complete").touch()
    return root, out


def _free_box(occupied: np.ndarray, rng: np.random.Generator) -> tuple[slice, slice, slice]:
    """A floater's box of voxels (slices; module docstring) where the grid is empty (an empty box after 50 tries)."""
    v = DEFAULT_GRID.voxel_size
    for _ in range(50):
        distance, azimuth = rng.uniform(4.0, 35.0), rng.uniform(-np.pi, np.pi)
        size = (rng.uniform(0.5, 2.5), rng.uniform(0.5, 2.5), int(rng.integers(1, 4)) * v)
        corner = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), rng.uniform(-0.25, 1.5)])
        lo = np.floor((corner - DEFAULT_GRID.lower) / v).astype(int)
        hi = lo + np.maximum(np.round(np.array(size) / v).astype(int), 1)
        if np.all(lo >= 0) and np.all(hi <= DEFAULT_GRID.shape):
            box = tuple(slice(a, b) for a, b in zip(lo, hi))
            if not occupied[box].any():
                return box
    return (slice(0, 0),) * 3


def degrade(grid: np.ndarray, kind: str, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """(damaged copy of a uint8 [x, y, z] grid, the damage's magnitude in its own unit) (module docstring)."""
    out = grid.copy()
    occupied = out != EMPTY
    if kind == "floaters":
        count = int(rng.integers(1, 13))
        for _ in range(count):
            out[_free_box(out != EMPTY, rng)] = OTHER
        return out, float(count)
    if kind == "wall_gap":
        width = rng.uniform(10.0, 120.0)
        centre = rng.uniform(-180.0, 180.0)
        x, y = np.meshgrid(*(DEFAULT_GRID.lower[a] + (np.arange(DEFAULT_GRID.shape[a]) + 0.5) * DEFAULT_GRID.voxel_size
                             for a in (0, 1)), indexing="ij")
        wedge = np.abs((np.degrees(np.arctan2(y, x)) - centre + 180.0) % 360.0 - 180.0) < width / 2
        above = int(round((0.0 - DEFAULT_GRID.z_min) / DEFAULT_GRID.voxel_size))
        out[:, :, above:][wedge] = EMPTY
        return out, width
    if kind == "drop":
        share = rng.uniform(0.05, 0.5)
        index = np.flatnonzero(occupied)
        out.reshape(-1)[rng.choice(index, int(share * len(index)), replace=False)] = EMPTY
        return out, share
    if kind == "shift":
        dx, dy = (int(rng.integers(1, 7)) * int(rng.choice([-1, 1])) for _ in range(2))
        out = np.roll(grid, (dx, dy), axis=(0, 1))
        return out, float(np.hypot(dx, dy) * DEFAULT_GRID.voxel_size)
    if kind == "trail":
        length = int(rng.integers(1, 17))
        vehicle = grid == VEHICLE
        for k in range(1, length + 1):
            moved = np.zeros_like(vehicle)
            moved[:-k] = vehicle[k:]
            out[moved & (out == EMPTY)] = VEHICLE
        return out, length * DEFAULT_GRID.voxel_size
    if kind == "ghost":
        lift = int(rng.integers(4, 9))
        ground = np.isin(grid, GROUND_IDS)
        angle = rng.uniform(0, 2 * np.pi)
        x, y = np.meshgrid(*(np.arange(n) - n // 2 for n in DEFAULT_GRID.shape[:2]), indexing="ij")
        ground &= ((x * np.cos(angle) + y * np.sin(angle)) > 0)[:, :, None]
        lifted = np.zeros_like(ground)
        lifted[:, :, lift:] = ground[:, :, :-lift]
        out[lifted & (out == EMPTY)] = OTHER
        return out, lift * DEFAULT_GRID.voxel_size
    return out, 0.0


def score_world(root: Path, out: Path, seed: int, max_rays: int) -> list[dict[str, Any]]:
    """Per frame of the world: damage kind and magnitude, true IoU / mIoU, ray figures (module docstring),
    plus the ray figures of the truth grid itself (keys truth_<figure>)."""
    from nuplan_occ.stages import PIPELINE

    built, truth = open_dataset(str(out)), open_dataset(str(root / "truth"))
    (frames,) = scene_frames(built).values()
    rng = np.random.default_rng(seed)
    plan = {token: KINDS[int(rng.integers(len(KINDS)))] for token in frames}
    truths: dict[str, dict] = {}
    damage: dict[str, dict] = {}

    def truth_of(token: str) -> dict:
        if token not in truths:
            truths.clear()
            truths[token] = truth.get(truth.index_of_token(token), keys=("semantics", "mask_lidar"))
        return truths[token]

    def damaged(token: str) -> np.ndarray:
        grid = built.get(built.index_of_token(token), keys=("semantics",))["semantics"]
        kind = plan[token]
        grid, magnitude = degrade(grid, kind, np.random.default_rng([seed, int(token[:8], 16)]))
        t = truth_of(token)
        figures = occupancy_metrics(grid, t["semantics"], t["mask_lidar"])
        damage[token] = {"kind": kind, "magnitude": magnitude, "iou": figures["iou"], "miou": figures["miou"]}
        return grid

    (task,) = scene_tasks(str(out), PIPELINE, root, None, None)
    rows = score_scene(task, PIPELINE, frames, damaged, max_rays)
    perfect = {r["token"]: r for r in score_scene(task, PIPELINE, frames,
                                                  lambda token: truth_of(token)["semantics"], max_rays)}
    for row in rows:
        row.update(damage[row["token"]], seed=seed,
                   **{f"truth_{column}": perfect[row["token"]][column] for column in FIGURES})
    return rows


def scoring_cost(root: Path, out: Path, max_rays: int) -> dict[str, float]:
    """CPU seconds per frame of what the write stage adds for the qa_ray_* columns (`frame_ray_columns`: the
    sweep moved into the frame, its rays walked; grid and sweep in memory), over every frame of the world's
    scene, with max_rays and with every return."""
    from nuplan_occ.pipeline.runner import run_stages
    from nuplan_occ.stages import PIPELINE

    built = open_dataset(str(out))
    (task,) = scene_tasks(str(out), PIPELINE, root, None, None)
    scene = run_stages(task, PIPELINE, ("scene",))["scene"]
    (frames,) = scene_frames(built).values()
    poses, _ = scene_poses(task, PIPELINE, scene, {t: f["ego_to_global"] for t, f in frames.items()})
    outputs = [p for p in scene.output_positions() if scene.sweeps[p].token in frames]
    cost = {}
    for limit in (max_rays, None):
        seconds = 0.0
        for position in outputs:
            grid = built.get(built.index_of_token(scene.sweeps[position].token), keys=("semantics",))["semantics"]
            scene.sweeps[scoring_sweep(scene, position)].xyz  # read before the clock starts: a build holds it
            started = time.process_time()
            frame_ray_columns(scene, position, poses, grid, None, limit)
            seconds += time.process_time() - started
        cost["cpu_s_per_frame" if limit else "cpu_s_per_frame_all_returns"] = seconds / len(outputs)
    return cost


def correlations(rows: list[dict]) -> dict[str, float]:
    """Spearman rho of each ray figure against the true IoU over `rows` (NaN figures left out)."""
    out = {}
    for column in FIGURES:
        pairs = np.array([(r[column], r["iou"]) for r in rows if r.get(column) is not None and np.isfinite(r[column])
                          and np.isfinite(r["iou"])])
        out[column] = float(spearmanr(pairs[:, 0], pairs[:, 1])[0]) if len(pairs) > 2 else float("nan")
    return out


def flag_table(rows: list[dict]) -> dict[str, dict]:
    """Per flag rule (and any flag): frames caught, their median true IoU and that of the rest, and the
    undamaged frames (kind none: the build as it is) caught."""
    out = {}
    undamaged = np.array([r["kind"] == "none" for r in rows])
    for name in [*FLAG_RULES, "any"]:
        caught = [bool(frame_flags(r)) if name == "any" else name in frame_flags(r) for r in rows]
        ious = np.array([r["iou"] for r in rows])
        hit = np.array(caught)
        out[name] = {"frames": int(hit.sum()), "of": len(rows), "undamaged": int((hit & undamaged).sum()),
                     "of_undamaged": int(undamaged.sum()),
                     "median_iou_caught": float(np.median(ious[hit])) if hit.any() else float("nan"),
                     "median_iou_rest": float(np.median(ious[~hit])) if (~hit).any() else float("nan")}
    return out


def summarize(rows: list[dict]) -> dict[str, Any]:
    by_kind = {}
    for kind in KINDS:
        subset = [r for r in rows if r["kind"] == kind]
        if subset:
            by_kind[kind] = {"frames": len(subset), "median_iou": float(np.median([r["iou"] for r in subset])),
                             **{f"median_{c}": float(np.nanmedian([r[c] for r in subset])) for c in FIGURES},
                             "spearman_vs_iou": correlations(subset) if kind != "none" else {}}
    truth_floor = {c: float(np.nanmedian([r[f"truth_{c}"] for r in rows])) for c in FIGURES}
    return {"frames": len(rows), "worlds": sorted({r["seed"] for r in rows}), "spearman_vs_iou": correlations(rows),
            "spearman_vs_miou": {c: float(spearmanr([r[c] for r in rows], [r["miou"] for r in rows])[0])
                                 for c in FIGURES},
            "by_kind": by_kind, "truth_floor": truth_floor, "flags": flag_table(rows)}


def _pct(value: float) -> str:
    return "n/a" if value != value else f"{100 * value:.1f}"


def render_markdown(report: dict) -> str:
    s = report["summary"]
    lines = [
        "# Ray consistency against truth",
        "",
        f"`python -m benchmarks.ray_consistency` ({report['seconds']:g} s `{PRESET}` worlds, seeds "
        f"{', '.join(map(str, s['worlds']))}; {s['frames']} frames; at most {report['max_rays']:,} returns scored "
        f"per frame; {report['machine']}). Figures: `nuplan_occ/rays/consistency.py`; damages: the module "
        "docstring of `benchmarks/ray_consistency.py`.",
        "",
        "## Rank correlation with the true IoU (Spearman, all frames of all worlds)",
        "",
        "| figure | rho vs IoU | rho vs mIoU |",
        "|---|---:|---:|",
        *(f"| {c} | {s['spearman_vs_iou'][c]:+.3f} | {s['spearman_vs_miou'][c]:+.3f} |" for c in FIGURES),
        "",
        "## Per damage kind (medians; rho within the kind)",
        "",
        "| kind | frames | IoU | agree % | early % | hole % | other % | depth p99 m | rho(agree, IoU) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for kind, k in s["by_kind"].items():
        rho = k["spearman_vs_iou"].get("qa_ray_agree", float("nan"))
        lines.append(f"| {kind} | {k['frames']} | {k['median_iou']:.3f} | {_pct(k['median_qa_ray_agree'])} | "
                     f"{_pct(k['median_qa_ray_early'])} | {_pct(k['median_qa_ray_hole'])} | "
                     f"{_pct(k['median_qa_ray_other'])} | {k['median_qa_ray_depth_error_p99_m']:.2f} | "
                     f"{'' if rho != rho else f'{rho:+.2f}'} |")
    floor = s["truth_floor"]
    lines += [
        "",
        f"The exact truth grids scored the same way (the floor of a perfect grid, medians): agree "
        f"{_pct(floor['qa_ray_agree'])} %, early {_pct(floor['qa_ray_early'])} %, hole {_pct(floor['qa_ray_hole'])} %, "
        f"other {_pct(floor['qa_ray_other'])} %.",
        "",
        "## Flag rules (nuplan_occ/rays/consistency.py FLAG_RULES): true IoU of the frames caught vs the rest",
        "",
        "| rule | when | frames caught | median IoU caught | median IoU rest | undamaged frames caught |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for name, f in s["flags"].items():
        rule = FLAG_RULES.get(name)
        when = f"qa_ray_{rule[0]} {rule[1]} {rule[2]:g}" if rule else "any rule"
        lines.append(f"| {name} | {when} | {f['frames']} of {f['of']} | {f['median_iou_caught']:.3f} | "
                     f"{f['median_iou_rest']:.3f} | {f['undamaged']} of {f['of_undamaged']} |")
    cost = report["cost"]
    lines += [
        "",
        "## Cost (CPU seconds per frame, mean over the worlds)",
        "",
        f"- What a build would add to score its own frames (the sweep moved into the frame and its rays walked; "
        f"grid and sweep in memory): {cost['cpu_s_per_frame']:.3f} with at most {report['max_rays']:,} returns, "
        f"{cost['cpu_s_per_frame_all_returns']:.3f} with every return.",
        f"- `nuplan-occ qa` on a finished build, end to end (the scene's sweeps read, grids decoded, files "
        f"written): {cost['qa_cpu_s_per_frame']:.3f}.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--max-rays", type=int, default=20000)
    parser.add_argument("--cache", type=Path, default=Path("bench/ray_worlds"))
    parser.add_argument("--out", type=Path, default=Path("bench"))
    args = parser.parse_args(argv)
    from nuplan_occ.stages import PIPELINE

    rows, costs = [], []
    for seed in args.seeds:
        root, out = world(args.cache, seed, args.seconds)
        rows += score_world(root, out, seed, args.max_rays)
        cost = scoring_cost(root, out, args.max_rays)
        started = time.process_time()
        frames = len(qa_dataset(str(out), root, PIPELINE, max_rays=args.max_rays, force=True).rows)
        costs.append({**cost, "qa_cpu_s_per_frame": (time.process_time() - started) / frames})
    report = {"seconds": args.seconds, "max_rays": args.max_rays, "machine": f"{platform.machine()}, "
              f"{platform.python_version()}", "summary": summarize(rows),
              "cost": {key: float(np.mean([c[key] for c in costs])) for key in costs[0]}, "frames": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report-ray-consistency.json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    (args.out / "report-ray-consistency.md").write_text(render_markdown(report))
    print(render_markdown(report))


if __name__ == "__main__":
    main()
