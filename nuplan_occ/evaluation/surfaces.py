"""Surface and occupancy quality metrics.

Points of both arguments must be in the same frame (metres). `surface_metrics` compares dense
samples of two surfaces (use `Surface.sample_points` at a spacing well below the thresholds).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from nuplan_occ.grid import GridSpec


def surface_metrics(pred_points: np.ndarray, truth_points: np.ndarray, thresholds: tuple[float, ...] = (0.1, 0.25)) -> dict:
    """Chamfer distance and precision / recall / F-score at each threshold (metres).

    accuracy = mean distance pred -> truth, completeness = mean distance truth -> pred,
    chamfer = their mean; precision@t = share of pred points within t of truth, recall@t = share
    of truth points within t of pred, fscore@t = harmonic mean. An empty prediction scores
    chamfer = inf and zero precision / recall / F-score.
    """
    pred = np.asarray(pred_points, dtype=np.float64).reshape(-1, 3)
    truth = np.asarray(truth_points, dtype=np.float64).reshape(-1, 3)
    if len(truth) == 0:
        raise ValueError("surface_metrics: truth_points is empty")
    result: dict = {"pred_points": len(pred), "truth_points": len(truth)}
    if len(pred) == 0:
        result.update(accuracy=np.inf, completeness=np.inf, chamfer=np.inf)
        for t in thresholds:
            result.update({f"precision@{t}": 0.0, f"recall@{t}": 0.0, f"fscore@{t}": 0.0})
        return result
    to_truth, _ = cKDTree(truth).query(pred, k=1)
    to_pred, _ = cKDTree(pred).query(truth, k=1)
    result.update(
        accuracy=float(to_truth.mean()),
        completeness=float(to_pred.mean()),
        chamfer=float(0.5 * (to_truth.mean() + to_pred.mean())),
    )
    for t in thresholds:
        precision = float(np.mean(to_truth < t))
        recall = float(np.mean(to_pred < t))
        fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
        result.update({f"precision@{t}": precision, f"recall@{t}": recall, f"fscore@{t}": fscore})
    return result


def occupancy(points: np.ndarray, grid: GridSpec) -> np.ndarray:
    """Bool volume of grid.shape: voxels containing at least one of `points` (grid frame, metres)."""
    volume = np.zeros(grid.shape, dtype=bool)
    idx, inside = grid.point_to_index(points)
    idx = idx[inside]
    volume[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return volume


def voxel_iou(pred_points: np.ndarray, truth_points: np.ndarray, grid: GridSpec, observable_mask: np.ndarray | None = None) -> float:
    """IoU of the voxels occupied by pred and truth points (both in the grid's frame, metres),
    counted only where `observable_mask` (bool, grid.shape) is True. Two empty sets give 1.0."""
    pred = occupancy(pred_points, grid)
    truth = occupancy(truth_points, grid)
    if observable_mask is not None:
        if observable_mask.shape != pred.shape:
            raise ValueError(f"voxel_iou: observable_mask shape {observable_mask.shape} != grid shape {pred.shape}")
        pred &= observable_mask
        truth &= observable_mask
    union = np.count_nonzero(pred | truth)
    return 1.0 if union == 0 else float(np.count_nonzero(pred & truth) / union)
