"""F-score of occupied voxel centres, as Occ3D-style benchmarks report it beside mIoU.

Per frame: the centres (metres, the grid's ego frame) of the occupied voxels (label != 0) of prediction
and truth inside the mask (voxels outside it are dropped from both). precision = share of predicted
centres closer than `threshold_m` to a truth centre; recall = share of truth centres closer than
`threshold_m` to a predicted centre (strict <); F = 2 P R / (P + R). Benchmarks average F over frames.
An empty prediction against a non-empty truth scores 0, as does a non-empty prediction against an empty
truth; both empty gives NaN (nothing to score; left out of the mean).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.evaluation.surfaces import surface_metrics
from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import EMPTY

THRESHOLD_M = 0.6
"""Distance below which a centre counts as matched (metres; the value Occ3D-style F-scores use)."""


def occupied_centres(semantics: np.ndarray, grid: GridSpec, mask: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) centres (m, ego frame) of the voxels with label != 0, inside `mask` (bool) when given."""
    occupied = np.asarray(semantics) != EMPTY
    if mask is not None:
        occupied &= np.asarray(mask, dtype=bool)
    return grid.index_to_center(np.argwhere(occupied))


def voxel_fscore(pred: np.ndarray, truth: np.ndarray, grid: GridSpec, mask: np.ndarray | None = None,
                 threshold_m: float = THRESHOLD_M) -> dict:
    """{"precision", "recall", "fscore"} of one frame's uint8 (X, Y, Z) grids of `grid` (module docstring)."""
    pred_pts, truth_pts = occupied_centres(pred, grid, mask), occupied_centres(truth, grid, mask)
    if not len(truth_pts):
        nan = float("nan")
        return {"precision": 0.0 if len(pred_pts) else nan, "recall": nan, "fscore": 0.0 if len(pred_pts) else nan}
    figures = surface_metrics(pred_pts, truth_pts, (threshold_m,))
    return {name: float(figures[f"{name}@{threshold_m}"]) for name in ("precision", "recall", "fscore")}
