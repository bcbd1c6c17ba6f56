"""Occ3D-style mIoU of one summed confusion matrix (the figure occupancy benchmarks rank by).

The confusion matrix counts every evaluated voxel, free ones included: `datasets.confusion(pred, truth,
mask)` per frame, summed over the frames, with the voxels outside the chosen mask (mask_camera or
mask_lidar; all voxels for "none") left out before counting. Free (id 0) is a class of the matrix, so a
voxel predicted free where the truth has a car counts against the car, but free is left out of the mean.
Per class c: IoU_c = M[c, c] / (sum of row c + sum of column c - M[c, c]) with M[truth id, pred id]. A class
absent from both truth and prediction (union 0) has IoU NaN and is left out of the mean; a class present in
the prediction only has IoU 0 and counts. mIoU = mean of the finite IoU_c over the non-free class ids.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.labels import EMPTY


def class_iou(conf: np.ndarray, class_id: int) -> float:
    """IoU of one id in a confusion matrix [truth id, pred id]; NaN where neither has that id."""
    union = int(conf[class_id, :].sum() + conf[:, class_id].sum() - conf[class_id, class_id])
    return float(conf[class_id, class_id] / union) if union else float("nan")


def occ3d_miou(conf: np.ndarray, class_ids: list[int]) -> dict:
    """Occ3D-style figures of a summed (N, N) confusion matrix [truth id, pred id] (module docstring).

    class_ids: the non-free ids scored (the dataset's label ids; EMPTY is dropped if given).
    Returns {"per_class": {id: IoU or NaN}, "miou": mean of the finite per-class IoUs (NaN if none),
    "free_iou": IoU of the free id, "geometry_iou": occupied-vs-free IoU (any non-free id counts as
    occupied), "n_voxels": voxels counted}.
    """
    conf = np.asarray(conf, dtype=np.int64)
    per_class = {int(c): class_iou(conf, int(c)) for c in class_ids if c != EMPTY}
    finite = [v for v in per_class.values() if np.isfinite(v)]
    occupied_both = int(np.delete(np.delete(conf, EMPTY, axis=0), EMPTY, axis=1).sum())
    occupied_union = int(conf.sum() - conf[EMPTY, EMPTY])
    return {
        "per_class": per_class,
        "miou": float(np.mean(finite)) if finite else float("nan"),
        "free_iou": class_iou(conf, EMPTY),
        "geometry_iou": occupied_both / occupied_union if occupied_union else float("nan"),
        "n_voxels": int(conf.sum()),
    }
