"""Compare a built dataset with a truth dataset (e.g. the synthetic worlds' exact grids), frame by frame.

Frames are matched by lidar_pc `token`; only tokens present (status ok) in both datasets count, so a
20 Hz truth can score a 10 Hz build. Both grids must be the same GridSpec (same ego frame, [x, y, z]).
Voxels are counted inside the truth's observability mask (`mask_lidar` of the TRUTH frame by default)
when the truth frame has it, else everywhere.

Per frame: `nuplan_occ.evaluation.grid_metrics.occupancy_metrics` (occupied-vs-empty IoU, per-class IoU, mIoU over
the classes present in that frame's truth). Dataset totals are pooled: intersections and unions are
summed over all frames before dividing (as Occ3D-style benchmarks accumulate one confusion matrix),
with mIoU over the classes present anywhere in the evaluated truth; the means of the per-frame
figures are reported too.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nuplan_occ.dataset import open_dataset
from nuplan_occ.labels import EMPTY
from nuplan_occ.evaluation.grid_metrics import occupancy_metrics

NO_MASK = "none"
N_IDS = 256


class EvaluationError(ValueError):
    """The two datasets cannot be compared (different grids, no common frame, unknown mask)."""


def confusion(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(256, 256) int64 voxel counts [truth id, pred id] of two uint8 grids, inside `mask` (bool)."""
    t = np.asarray(truth, dtype=np.int64)
    p = np.asarray(pred, dtype=np.int64)
    if mask is not None:
        t, p = t[mask], p[mask]
    return np.bincount((t * N_IDS + p).reshape(-1), minlength=N_IDS * N_IDS).reshape(N_IDS, N_IDS)


def pooled_metrics(conf: np.ndarray, class_ids: list[int]) -> dict:
    """IoU figures of a summed confusion matrix [truth, pred].

    Returns {"iou", "per_class": {id: IoU (NaN if the class is in neither)}, "miou" over the classes
    with truth voxels, "n_voxels"}.
    """
    truth_n, pred_n, inter = conf.sum(axis=1), conf.sum(axis=0), np.diag(conf)
    occ_inter = int(conf[1:, 1:].sum())
    occ_union = int(conf.sum() - conf[EMPTY, EMPTY])
    per_class = {}
    for c in class_ids:
        union = int(truth_n[c] + pred_n[c] - inter[c])
        per_class[int(c)] = float(inter[c] / union) if union else float("nan")
    present = [c for c in per_class if truth_n[c] > 0]
    return {
        "iou": occ_inter / occ_union if occ_union else float("nan"),
        "per_class": per_class,
        "miou": float(np.mean([per_class[c] for c in present])) if present else float("nan"),
        "n_voxels": int(conf.sum()),
    }


def finite_mean(values: list[float]) -> float:
    """Mean of the finite values; NaN if there is none."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _nan_to_none(value):
    """JSON-safe copy: NaN floats become None, dict keys strings."""
    if isinstance(value, dict):
        return {str(k): _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def write_json(result: dict, json_path: Path) -> None:
    """Write an evaluation result as indented JSON (NaN as null, keys as strings), creating the folder."""
    Path(json_path).parent.mkdir(parents=True, exist_ok=True)
    Path(json_path).write_text(json.dumps(_nan_to_none(result), indent=2, allow_nan=False) + "\n")


def evaluate(built_root: str, truth_root: str, mask: str = "mask_lidar", json_path: Path | None = None) -> dict:
    """Score `built_root` against `truth_root` (see module docstring); optionally write the result as JSON.

    mask: the truth member restricting the evaluated voxels ("mask_lidar", "mask_camera") or "none".
    Returns {"built", "truth", "mask", "frames_built", "frames_truth", "frames_matched",
    "frames_without_mask", "class_names", "pooled": {...}, "mean_frame_iou", "mean_frame_miou",
    "frames": [{"token", "log_name", "iou", "miou", "n_occupied_built", "n_occupied_truth", "n_voxels"}]}.
    """
    if mask not in (NO_MASK, "mask_lidar", "mask_camera"):
        raise EvaluationError(f"mask {mask!r}: use mask_lidar, mask_camera or {NO_MASK}")
    built, truth = open_dataset(built_root), open_dataset(truth_root)
    if built.grid != truth.grid:
        raise EvaluationError(f"{built_root} grid {built.grid} differs from {truth_root} grid {truth.grid}")
    truth_tokens = set(truth.manifest["token"].to_pylist())
    matched = [(i, t) for i, t in enumerate(built.manifest["token"].to_pylist()) if t in truth_tokens]
    if not matched:
        raise EvaluationError(f"{built_root} and {truth_root} have no ok frame token in common")
    class_ids = sorted((set(built.labels) | set(truth.labels)) - {EMPTY})
    total = np.zeros((N_IDS, N_IDS), dtype=np.int64)
    frames, without_mask = [], 0
    for i, token in matched:
        j = truth.index_of_token(token)
        pred = built.get(i, keys=("semantics",))["semantics"]
        has_mask = mask != NO_MASK and mask in truth.members_of(j)
        keys = ("semantics", mask) if has_mask else ("semantics",)
        truth_frame = truth.get(j, keys=keys)
        region = truth_frame[mask] if has_mask else None
        without_mask += mask != NO_MASK and not has_mask
        figures = occupancy_metrics(pred, truth_frame["semantics"], region, class_ids)
        total += confusion(pred, truth_frame["semantics"], region)
        frames.append({
            "token": token,
            "log_name": truth_frame["log_name"],
            "iou": figures["iou"],
            "miou": figures["miou"],
            "n_occupied_built": int(np.count_nonzero(pred)),
            "n_occupied_truth": int(np.count_nonzero(truth_frame["semantics"])),
            "n_voxels": figures["n_voxels"],
        })
    result = {
        "built": built_root,
        "truth": truth_root,
        "mask": mask,
        "frames_built": len(built),
        "frames_truth": len(truth),
        "frames_matched": len(matched),
        "frames_without_mask": int(without_mask),
        "class_names": {c: truth.labels.get(c, built.labels.get(c))["name"] for c in class_ids},
        "pooled": pooled_metrics(total, class_ids),
        "mean_frame_iou": finite_mean([f["iou"] for f in frames]),
        "mean_frame_miou": finite_mean([f["miou"] for f in frames]),
        "frames": frames,
    }
    if json_path is not None:
        write_json(result, json_path)
    return result
