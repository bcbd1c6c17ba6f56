"""evaluate(): frames matched by token, IoU inside the truth's mask_lidar, analytic figures."""

import json

import numpy as np
import pytest

from nuplan_occ.evaluation.datasets import EvaluationError, confusion, evaluate, pooled_metrics
from nuplan_occ.labels import EMPTY, OTHER, PEDESTRIAN, ROAD, VEHICLE
from nuplan_occ.evaluation.grid_metrics import occupancy_metrics
from tools_world import SMALL, small_scene, token_of, write_dataset


def _mask() -> np.ndarray:
    """Observed: x index < 24 (the last 8 x-columns are unobserved)."""
    mask = np.zeros(SMALL.shape, dtype=bool)
    mask[:24] = True
    return mask


@pytest.fixture(scope="module")
def truth_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("truth")
    write_dataset(root, [{"semantics": small_scene(i), "mask_lidar": _mask()} for i in range(4)])
    return str(root)


def test_dataset_against_itself_scores_one(truth_root, tmp_path):
    result = evaluate(truth_root, truth_root, json_path=tmp_path / "eval.json")
    assert result["frames_matched"] == 4 and result["frames_without_mask"] == 0
    assert result["pooled"]["iou"] == 1.0 and result["pooled"]["miou"] == 1.0
    assert all(f["iou"] == 1.0 and f["miou"] == 1.0 for f in result["frames"])
    assert result["pooled"]["n_voxels"] == 4 * _mask().sum()
    saved = json.loads((tmp_path / "eval.json").read_text())
    assert saved["pooled"]["iou"] == 1.0 and len(saved["frames"]) == 4
    assert saved["pooled"]["per_class"][str(PEDESTRIAN)] == 1.0


def test_perturbed_copy_gives_the_analytic_iou(truth_root, tmp_path):
    """Built = frames 1 and 3 of the truth (plus a frame the truth lacks), perturbed:
    k vehicle voxels removed, m road voxels added in free space, r road voxels relabelled other,
    and changes outside the truth's mask (must not count)."""
    rng = np.random.default_rng(7)
    built_frames, expected = [None] * 6, {}
    totals = {"inter_occ": 0, "union_occ": 0, "veh_i": 0, "veh_u": 0, "road_i": 0, "road_u": 0}
    mask = _mask()
    for i in (1, 3):
        truth = small_scene(i)
        pred = truth.copy()
        inside = np.zeros_like(mask)
        inside[:24] = True
        vehicles = np.argwhere((truth == VEHICLE) & inside)
        free = np.argwhere((truth == EMPTY) & inside)
        road = np.argwhere((truth == ROAD) & inside)
        k, m, r = 5 + i, 11 + i, 3 * i
        for arr, sel, value in ((vehicles, k, EMPTY), (free, m, ROAD), (road, r, OTHER)):
            idx = arr[rng.choice(len(arr), sel, replace=False)]
            pred[tuple(idx.T)] = value
        pred[26:, :, 5] = VEHICLE  # outside the mask: ignored
        built_frames[i] = {"semantics": pred}
        n, v, rd = (truth[mask] != EMPTY).sum(), (truth[mask] == VEHICLE).sum(), (truth[mask] == ROAD).sum()
        expected[token_of(i)] = ((n - k) / (n + m), (v - k) / v, (rd - r) / (rd + m))
        for key, value in (("inter_occ", n - k), ("union_occ", n + m), ("veh_i", v - k), ("veh_u", v),
                           ("road_i", rd - r), ("road_u", rd + m)):
            totals[key] += value
    built_frames[5] = {"semantics": small_scene(99)}  # token not in the truth: not scored
    write_dataset(tmp_path / "built", built_frames)
    result = evaluate(str(tmp_path / "built"), truth_root)
    assert result["frames_built"] == 3 and result["frames_matched"] == 2 and result["frames_truth"] == 4
    for frame in result["frames"]:
        occ, veh, road = expected[frame["token"]]
        assert frame["iou"] == pytest.approx(occ)
        assert frame["n_occupied_truth"] == np.count_nonzero(small_scene(int(frame["token"], 16)))
    pooled = result["pooled"]
    assert pooled["iou"] == pytest.approx(totals["inter_occ"] / totals["union_occ"])
    assert pooled["per_class"][VEHICLE] == pytest.approx(totals["veh_i"] / totals["veh_u"])
    assert pooled["per_class"][ROAD] == pytest.approx(totals["road_i"] / totals["road_u"])
    assert pooled["per_class"][PEDESTRIAN] == 1.0
    # without the mask the unobserved vehicle slab counts as false positives
    unmasked = evaluate(str(tmp_path / "built"), truth_root, mask="none")
    assert unmasked["pooled"]["iou"] < pooled["iou"]


def test_pooled_counts_of_one_frame_equal_occupancy_metrics():
    pred, truth = small_scene(1), small_scene(2)
    mask = _mask()
    ids = [OTHER, VEHICLE, PEDESTRIAN, ROAD, 13]
    ours = pooled_metrics(confusion(pred, truth, mask), ids)
    theirs = occupancy_metrics(pred, truth, mask, ids)
    assert ours["iou"] == pytest.approx(theirs["iou"]) and ours["miou"] == pytest.approx(theirs["miou"])
    assert all(ours["per_class"][c] == pytest.approx(theirs["per_class"][c]) for c in ids)


def test_no_common_token_and_bad_mask_are_errors(truth_root, tmp_path):
    write_dataset(tmp_path / "other", [None] * 9 + [{"semantics": small_scene(0)}])
    with pytest.raises(EvaluationError, match="no ok frame token in common"):
        evaluate(str(tmp_path / "other"), truth_root)
    with pytest.raises(EvaluationError, match="mask"):
        evaluate(truth_root, truth_root, mask="lidar")
