"""The bench's quality summary: medians over frames, and pooled figures that weigh a class by its voxels."""

from __future__ import annotations

import numpy as np

from benchmarks.small import summarize_metrics
from nuplan_occ.evaluation.datasets import N_IDS, confusion
from nuplan_occ.labels import LABELS, VEHICLE
from nuplan_occ.evaluation.grid_metrics import occupancy_metrics


def test_pooled_vehicle_weighs_by_voxels_where_the_median_cannot() -> None:
    """Three frames: a small vehicle found exactly in one, a big one missed entirely in two. The median of
    per-frame IoU says 0; pooled, the class scores its found voxels over all its voxels."""
    shape = (8, 8, 4)
    frames = []
    small = np.zeros(shape, np.uint8)
    small[0, 0, 0] = VEHICLE
    big = np.zeros(shape, np.uint8)
    big[:, :4, :2] = VEHICLE  # 64 voxels
    frames = [(small, small), (np.zeros(shape, np.uint8), big), (np.zeros(shape, np.uint8), big)]
    metrics = [occupancy_metrics(pred, truth) for pred, truth in frames]
    summed = np.zeros((N_IDS, N_IDS), np.int64)
    for pred, truth in frames:
        summed += confusion(pred, truth)
    without_big = np.zeros_like(summed)
    without_big += confusion(*frames[0])
    summary = summarize_metrics(metrics, [0, 0, 0], [0.0, 0.0, 0.0], summed, without_big)
    name = LABELS.names[VEHICLE]
    assert summary["per_class_iou"][name] == 0.0
    assert summary["pooled"]["per_class_iou"][name] == 1 / 129
    assert summary["pooled"]["miou"] == 1 / 129
    assert summary["pooled_annotated"]["per_class_iou"][name] == 1.0  # the confusion it is given
