"""Score model predictions against a dataset with the field's metrics, frame by frame, matched by token.

Predictions: a folder of per-token files (`nuplan_occ.evaluation.predictions`) or another dataset root
(its `semantics`). Truth: a dataset root; its ok frames give the truth grids, the masks and the poses of
each scene's frames (for the ray origins). Figures, all summed or averaged over the matched frames:
- Occ3D-style mIoU (`occ3d_miou`): one confusion matrix over the voxels inside the truth frame's mask
  (`mask_camera`, `mask_lidar`, or "none" = all voxels; a truth frame without that member is scored
  everywhere and counted in `frames_without_mask`);
- RayIoU at 1 / 2 / 4 m (`ray_iou`; no mask: the rays decide what is seen);
- F-score of occupied voxel centres (`voxel_fscore`, inside the same mask), the mean over frames.
A prediction on a stated grid is resampled to the truth's; voxels it does not cover are left out of
every figure (removed from the mask, and set free in both grids before the rays are cast).
Truth frames without a prediction and predictions without a truth frame are counted, not scored.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from nuplan_occ.dataset import open_dataset
from nuplan_occ.evaluation.datasets import NO_MASK, EvaluationError, finite_mean, confusion, write_json
from nuplan_occ.evaluation.occ3d_miou import occ3d_miou
from nuplan_occ.evaluation.predictions import find_predictions, load_prediction, parse_grid, resample
from nuplan_occ.evaluation.ray_iou import THRESHOLDS_M, RayCounts, cast_rays, ray_counts, ray_directions, ray_iou, \
    ray_origins
from nuplan_occ.evaluation.voxel_fscore import THRESHOLD_M, voxel_fscore
from nuplan_occ.labels import EMPTY
from nuplan_occ.storage.metadata import METADATA_NAME

MASKS = (NO_MASK, "mask_camera", "mask_lidar")
N_IDS = 256


def is_dataset_root(path: str) -> bool:
    """Whether `path` is a dataset root (a URL, or a folder holding dataset.json) rather than a prediction folder."""
    return "://" in path or (Path(path) / METADATA_NAME).is_file()


def _prediction_source(path: str, grid_text: str | None, labels: str, truth_grid) -> tuple:
    """(grid of the predictions, {token: loader () -> uint8 array}) of a prediction folder or dataset root."""
    if is_dataset_root(path):
        ds = open_dataset(path)
        tokens = ds.column("token").to_pylist()
        return ds.grid, {t: (lambda i=i: ds.get(i, keys=("semantics",))["semantics"]) for i, t in enumerate(tokens)}
    grid = parse_grid(grid_text, truth_grid)
    return grid, {t: (lambda p=p: load_prediction(p, grid.shape, labels)) for t, p in find_predictions(Path(path)).items()}


def _scene_poses(truth) -> dict[str, tuple[np.ndarray, int]]:
    """token -> (T_global_from_ego (F, 4, 4) of its scene's ok frames in time order, its position there)."""
    table = truth.columns(["token", "scene_token", "timestamp_us", "ego_to_global"]).to_pylist()
    scenes: dict = defaultdict(list)
    for row in table:
        scenes[row["scene_token"]].append(row)
    out = {}
    for rows in scenes.values():
        rows.sort(key=lambda r: (r["timestamp_us"] is None, r["timestamp_us"] or 0))
        poses = np.stack([np.full((4, 4), np.nan) if r["ego_to_global"] is None
                          else np.asarray(r["ego_to_global"], dtype=np.float64).reshape(4, 4) for r in rows])
        for k, r in enumerate(rows):
            out[r["token"]] = (poses, k)
    return out


def _check_ids(pred: np.ndarray, known: set[int], where: str) -> None:
    """EvaluationError naming `where` if `pred` holds ids outside `known`."""
    unknown = sorted(set(np.flatnonzero(np.bincount(pred.reshape(-1), minlength=N_IDS)).tolist()) - known)
    if unknown:
        raise EvaluationError(f"{where}: label ids {unknown} are not in the dataset's labels")


def evaluate_predictions(predictions: str, truth_root: str, mask: str = "mask_camera", pred_grid: str | None = None,
                         labels: str = "ours", rays: bool = True, fscore_threshold_m: float = THRESHOLD_M,
                         json_path: Path | None = None,
                         progress: Callable[[int, int], None] | None = None) -> dict:
    """Score `predictions` (folder or dataset root) against `truth_root` (module docstring).

    mask: "mask_camera", "mask_lidar" or "none"; pred_grid: the grid of the prediction files (None or
    "ours": the truth's; see `predictions.parse_grid`); labels: "ours" or "occ3d" (ids of the files);
    rays: compute RayIoU (the costliest figure); progress(done, total) after each frame.
    Returns {"predictions", "truth", "mask", "prediction_grid", "labels", "frames_matched",
    "truth_frames_without_prediction", "predictions_without_truth", "frames_without_mask", "class_names",
    "occ3d": `occ3d_miou` of the summed matrix, "rayiou": `ray_iou` of the summed counts (None without
    rays), "fscore": {"threshold_m", "fscore", "precision", "recall"} means over frames,
    "frames": [{"token", "log_name", "miou", "rayiou", "fscore", "precision", "recall"}]}; written as JSON
    to json_path when given (NaN as null).
    """
    if mask not in MASKS:
        raise EvaluationError(f"mask {mask!r}: use {', '.join(MASKS)}")
    if labels not in ("ours", "occ3d"):
        raise EvaluationError(f"labels {labels!r}: use ours or occ3d")
    truth = open_dataset(truth_root)
    grid, loaders = _prediction_source(predictions, pred_grid, labels, truth.grid)
    truth_tokens = truth.column("token").to_pylist()
    matched = [t for t in dict.fromkeys(truth_tokens) if t in loaders]
    if not matched:
        raise EvaluationError(f"{predictions} and {truth_root} have no frame token in common")
    class_ids = sorted(set(truth.labels) - {EMPTY})
    known = set(truth.labels)
    poses = _scene_poses(truth) if rays else {}
    directions = ray_directions() if rays else None
    total, counts = np.zeros((N_IDS, N_IDS), dtype=np.int64), RayCounts.zeros(THRESHOLDS_M)
    frames, without_mask = [], 0
    for n, token in enumerate(matched):
        j = truth.index_of_token(token)
        has_mask = mask != NO_MASK and mask in truth.members_of(j)
        without_mask += mask != NO_MASK and not has_mask
        frame = truth.get(j, keys=("semantics", mask) if has_mask else ("semantics",))
        gt = frame["semantics"]
        pred, covered = resample(loaders[token](), grid, truth.grid)
        _check_ids(pred, known, f"prediction of {token}")
        region = frame[mask] if has_mask else None
        if covered is not None:
            region = covered if region is None else region & covered
            gt = np.where(covered, gt, EMPTY).astype(np.uint8)
        conf = confusion(pred, gt, region)
        total += conf
        fscore = voxel_fscore(pred, gt, truth.grid, region, fscore_threshold_m)
        record = {"token": token, "log_name": frame["log_name"], "miou": occ3d_miou(conf, class_ids)["miou"],
                  "rayiou": None, **fscore}
        if rays:
            scene_poses, k = poses[token]
            origins = ray_origins(scene_poses, k, truth.grid)
            frame_counts = ray_counts(*cast_rays(pred, origins, directions, truth.grid),
                                      *cast_rays(gt, origins, directions, truth.grid))
            counts = counts + frame_counts
            record["rayiou"] = ray_iou(frame_counts, class_ids)["rayiou"]
        frames.append(record)
        if progress is not None:
            progress(n + 1, len(matched))
    result = {
        "predictions": str(predictions),
        "truth": truth_root,
        "mask": mask,
        "prediction_grid": grid.to_dict(),
        "labels": labels,
        "frames_matched": len(matched),
        "truth_frames_without_prediction": len(set(truth_tokens) - set(loaders)),
        "predictions_without_truth": len(set(loaders) - set(truth_tokens)),
        "frames_without_mask": int(without_mask),
        "class_names": {c: truth.labels[c]["name"] for c in class_ids},
        "occ3d": occ3d_miou(total, class_ids),
        "rayiou": ray_iou(counts, class_ids) if rays else None,
        "fscore": {"threshold_m": fscore_threshold_m,
                   **{k: finite_mean([f[k] for f in frames]) for k in ("fscore", "precision", "recall")}},
        "frames": frames,
    }
    if json_path is not None:
        write_json(result, json_path)
    return result
