"""Quality figures of semantic occupancy grids. Pure numpy; grids are uint8 (X, Y, Z) label ids, 0 = empty."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import EMPTY
from nuplan_occ.voxel.voxelize import in_box


class MetricsError(ValueError):
    """Grids of mismatching shapes given to a metric."""


def _same_shape(name: str, *arrays: np.ndarray) -> None:
    shapes = {tuple(np.shape(a)) for a in arrays if a is not None}
    if len(shapes) > 1:
        raise MetricsError(f"{name}: arrays of different shapes {sorted(shapes)}")


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else float("nan")


def occupancy_metrics(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
                      class_ids=None) -> dict:
    """IoU figures of pred vs truth semantics, counted inside `mask` (bool, all voxels if None).

    Returns {"iou": occupied-vs-empty IoU, "per_class": {id: IoU} for class_ids (default: every
    non-empty id in pred or truth; NaN where a class is in neither), "miou": mean over the classes
    present in truth, "n_voxels": voxels evaluated}.
    """
    _same_shape("occupancy_metrics", pred, truth, mask)
    sel = np.ones(np.shape(truth), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    p, t = np.asarray(pred)[sel], np.asarray(truth)[sel]
    if class_ids is None:
        class_ids = sorted((set(np.unique(p).tolist()) | set(np.unique(t).tolist())) - {EMPTY})
    per_class = {int(c): _iou(p == c, t == c) for c in class_ids if c != EMPTY}
    present = [c for c in per_class if np.any(t == c)]
    miou = float(np.mean([per_class[c] for c in present])) if present else float("nan")
    return {"iou": _iou(p != EMPTY, t != EMPTY), "per_class": per_class, "miou": miou, "n_voxels": int(sel.sum())}


def trail_count(pred_semantics: np.ndarray, swept_mask: np.ndarray, current_object_mask: np.ndarray) -> int:
    """Occupied voxels inside space a box swept through at other times (swept_mask, bool) but that no
    current box occupies (current_object_mask, bool): ghost trails of moving objects."""
    _same_shape("trail_count", pred_semantics, swept_mask, current_object_mask)
    return int(np.count_nonzero((np.asarray(pred_semantics) != EMPTY) & swept_mask & ~current_object_mask))


def ground_hole_rate(pred_semantics: np.ndarray, drivable_columns_mask: np.ndarray, ground_height_index: np.ndarray,
                     tolerance_voxels: int = 1) -> float:
    """Fraction of drivable columns (bool (X, Y)) with a known ground layer index (int (X, Y), < 0 =
    unknown, excluded) that have no occupied voxel within +-tolerance_voxels of that layer. NaN if no
    column qualifies."""
    pred = np.asarray(pred_semantics)
    _same_shape("ground_hole_rate", pred.shape[:2], np.shape(drivable_columns_mask), np.shape(ground_height_index))
    k = np.asarray(ground_height_index)
    cols = np.asarray(drivable_columns_mask, dtype=bool) & (k >= 0)
    if not cols.any():
        return float("nan")
    z = np.arange(pred.shape[2])
    band = np.abs(z[None, None, :] - k[:, :, None]) <= tolerance_voxels
    has_ground = np.any((pred != EMPTY) & band, axis=2)
    return float(np.count_nonzero(cols & ~has_ground) / np.count_nonzero(cols))


def unannotated_objects(instance: np.ndarray, centers: np.ndarray, yaws: np.ndarray, sizes: np.ndarray,
                        grid: GridSpec = DEFAULT_GRID, grow_m: float = 1.0) -> np.ndarray:
    """bool (X, Y, Z): the voxels of object instances (uint16 (X, Y, Z) instance ids, 0 = none, e.g. a
    synthetic truth's) whose voxel centroid lies in none of the frame's annotated boxes (centers (K, 3),
    yaws (K,) rad, sizes (K, 3) m, ego frame of the grid) grown by grow_m: objects the log has no box for
    at that frame, which no method that reads the boxes can give a class."""
    inst = np.asarray(instance)
    index = np.argwhere(inst > 0)
    out = np.zeros(inst.shape, dtype=bool)
    if not len(index):
        return out
    ids, member = np.unique(inst[tuple(index.T)], return_inverse=True)
    centres = grid.index_to_center(index)
    centroids = np.stack([np.bincount(member, centres[:, a]) for a in range(3)], axis=1) / np.bincount(member)[:, None]
    boxed = np.zeros(len(ids), dtype=bool)
    for center, yaw, size in zip(np.reshape(centers, (-1, 3)), np.reshape(yaws, -1), np.reshape(sizes, (-1, 3))):
        boxed |= in_box(centroids, center, float(yaw), size, grow_m)
    unboxed = ids[~boxed]
    out[tuple(index[np.isin(inst[tuple(index.T)], unboxed)].T)] = True
    return out
