"""evaluate_predictions and `nuplan-occ eval` on a folder of predictions: file layouts, pooling, a stated
grid, Occ3D ids, and one clear error per bad file."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from nuplan_occ.cli.app import app
from nuplan_occ.evaluation.datasets import EvaluationError, confusion
from nuplan_occ.evaluation.occ3d_miou import occ3d_miou
from nuplan_occ.evaluation.prediction_eval import evaluate_predictions
from nuplan_occ.evaluation.ray_iou import RayCounts, cast_rays, ray_counts, ray_directions, ray_iou, ray_origins
from nuplan_occ.evaluation.voxel_fscore import voxel_fscore
from nuplan_occ.export.formats import to_occ3d
from nuplan_occ.labels import LABELS
from tools_world import SMALL, small_scene, token_of, write_dataset

COARSE_TEXT = "0,4,-4,4,-1,1,0.5"
"""The x >= 0 half of SMALL at 0.5 m voxels (8 x 16 x 4)."""


def _camera_mask() -> np.ndarray:
    mask = np.zeros(SMALL.shape, dtype=bool)
    mask[:24] = True
    return mask


def _coarse_scene(i: int) -> np.ndarray:
    """(16, 16, 4) random labels at 0.5 m over SMALL's box."""
    rng = np.random.default_rng(100 + i)
    ids = np.array([0, 0, 0, 0, 1, 2, 4, 12, 13])
    return ids[rng.integers(0, len(ids), (16, 16, 4))].astype(np.uint8)


def _truth_scene(i: int) -> np.ndarray:
    """Frame i of the truth: small_scene(i) on the x < 0 half, the coarse scene upsampled on the x >= 0 half."""
    sem = small_scene(i)
    sem[16:] = np.repeat(np.repeat(np.repeat(_coarse_scene(i)[8:], 2, 0), 2, 1), 2, 2)
    return sem


@pytest.fixture(scope="module")
def truth_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("truth")
    write_dataset(root, [{"semantics": _truth_scene(i), "mask_camera": _camera_mask()} for i in range(3)])
    return str(root)


def _perturbed(i: int) -> np.ndarray:
    pred = _truth_scene(i)
    rng = np.random.default_rng(i)
    pred[rng.random(pred.shape) < 0.05] = 0
    pred[rng.random(pred.shape) < 0.02] = 2
    return pred


def test_identical_predictions_in_every_layout_score_one(truth_root, tmp_path):
    np.save(tmp_path / f"{token_of(0)}.npy", _truth_scene(0))
    (tmp_path / "log" / token_of(2)).mkdir(parents=True)
    np.savez_compressed(tmp_path / "log" / token_of(2) / "labels.npz", pred=_truth_scene(2))
    np.savez(tmp_path / f"{token_of(7)}.npz", semantics=_truth_scene(1))  # no such truth frame
    result = evaluate_predictions(str(tmp_path), truth_root)
    assert result["frames_matched"] == 2 and result["mask"] == "mask_camera"
    assert result["truth_frames_without_prediction"] == 1 and result["predictions_without_truth"] == 1
    assert result["occ3d"]["miou"] == 1.0 and result["occ3d"]["geometry_iou"] == 1.0
    assert result["occ3d"]["n_voxels"] == 2 * _camera_mask().sum()
    assert result["rayiou"]["rayiou"] == 1.0 and result["rayiou"]["n_rays"] > 0
    assert result["fscore"]["fscore"] == 1.0 and [f["token"] for f in result["frames"]] == [token_of(0), token_of(2)]


def test_pooled_figures_equal_the_metrics_summed_by_hand(truth_root, tmp_path):
    for i in range(3):
        np.savez(tmp_path / f"{token_of(i)}.npz", semantics=_perturbed(i))
    result = evaluate_predictions(str(tmp_path), truth_root, json_path=tmp_path / "out" / "eval.json")
    class_ids = sorted(set(LABELS.names) - {0})
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = 1000.0 + np.arange(3)  # write_dataset's poses: one scene, 1 m apart
    conf, counts, fscores = 0, RayCounts.zeros(), []
    for i in range(3):
        pred, truth = _perturbed(i), _truth_scene(i)
        conf = conf + confusion(pred, truth, _camera_mask())
        fscores.append(voxel_fscore(pred, truth, SMALL, _camera_mask())["fscore"])
        origins = ray_origins(poses, i, SMALL)
        counts = counts + ray_counts(*cast_rays(pred, origins, ray_directions(), SMALL),
                                     *cast_rays(truth, origins, ray_directions(), SMALL))
    expected = occ3d_miou(conf, class_ids)
    assert result["occ3d"]["miou"] == pytest.approx(expected["miou"]) and 0.3 < expected["miou"] < 0.95
    assert result["rayiou"]["rayiou"] == pytest.approx(ray_iou(counts, class_ids)["rayiou"])
    assert result["fscore"]["fscore"] == pytest.approx(np.mean(fscores))
    saved = json.loads((tmp_path / "out" / "eval.json").read_text())
    assert saved["occ3d"]["miou"] == pytest.approx(expected["miou"]) and len(saved["frames"]) == 3
    assert saved["occ3d"]["per_class"]["6"] is None  # barrier: in neither grid
    assert set(saved["rayiou"]["miou"]) == {"1.0", "2.0", "4.0"}

    # the same predictions in the Occ3D ids our export writes score the same
    occ3d_dir = tmp_path / "occ3d"
    occ3d_dir.mkdir()
    for i in range(3):
        np.savez(occ3d_dir / f"{token_of(i)}.npz", semantics=to_occ3d(_perturbed(i)))
    again = evaluate_predictions(str(occ3d_dir), truth_root, labels="occ3d", rays=False)
    assert again["occ3d"]["miou"] == pytest.approx(expected["miou"]) and again["rayiou"] is None


def test_prediction_on_a_stated_grid_is_scored_where_it_covers(truth_root, tmp_path):
    """Predictions of the x >= 0 half at 0.5 m: resampled, they equal the truth there; the rest is not scored."""
    for i in range(3):
        np.save(tmp_path / f"{token_of(i)}.npy", _coarse_scene(i)[8:])
    result = evaluate_predictions(str(tmp_path), truth_root, mask="none", pred_grid=COARSE_TEXT)
    assert result["occ3d"]["n_voxels"] == 3 * 16 * 32 * 8
    assert result["occ3d"]["miou"] == 1.0 and result["fscore"]["fscore"] == 1.0 and result["rayiou"]["rayiou"] == 1.0
    with pytest.raises(EvaluationError, match=r"shape \(8, 16, 4\), the prediction grid has \(32, 32, 8\)"):
        evaluate_predictions(str(tmp_path), truth_root)


def _bad(path, writer) -> str:
    writer(path)
    return str(path)


@pytest.mark.parametrize("name, writer, message", [
    ("a.npz", lambda p: np.savez(p, occupancy=np.zeros(SMALL.shape, np.uint8)), "no array named semantics or pred"),
    ("a.npy", lambda p: np.save(p, np.zeros(SMALL.shape, np.float32)), "must be integers"),
    ("a.npy", lambda p: np.save(p, np.full(SMALL.shape, 9, np.uint8)), r"label ids \[9\]"),
    ("a.npy", lambda p: np.save(p, np.array([{"x": 1}], dtype=object), allow_pickle=True), "not a readable"),
    ("a.npz", lambda p: p.write_bytes(b"not a zip"), "not a readable"),
])
def test_a_bad_prediction_file_is_one_error_naming_it(truth_root, tmp_path, name, writer, message):
    path = tmp_path / name.replace("a", token_of(1), 1)
    _bad(path, writer)
    with pytest.raises(EvaluationError, match=message) as caught:
        evaluate_predictions(str(tmp_path), truth_root, rays=False)
    assert token_of(1) in str(caught.value)


def test_folder_and_option_errors(truth_root, tmp_path):
    with pytest.raises(EvaluationError, match="no .npz or .npy"):
        evaluate_predictions(str(tmp_path), truth_root)
    np.save(tmp_path / f"{token_of(1)}.npy", _truth_scene(1))
    (tmp_path / token_of(1)).mkdir()
    np.savez(tmp_path / token_of(1) / "labels.npz", semantics=_truth_scene(1))
    with pytest.raises(EvaluationError, match="also predicted by"):
        evaluate_predictions(str(tmp_path), truth_root)
    with pytest.raises(EvaluationError, match="prediction grid"):
        evaluate_predictions(str(tmp_path), truth_root, pred_grid="1,2,3")
    with pytest.raises(EvaluationError, match="mask"):
        evaluate_predictions(str(tmp_path), truth_root, mask="lidar")


def test_cli_prints_the_table_and_writes_json(truth_root, tmp_path):
    preds = tmp_path / "preds"
    preds.mkdir()
    for i in range(3):
        np.save(preds / f"{token_of(i)}.npy", _perturbed(i))
    runner = CliRunner()
    out = runner.invoke(app, ["eval", str(preds), truth_root, "--json", str(tmp_path / "e.json")],
                        env={"COLUMNS": "160"})
    assert out.exit_code == 0, out.output
    assert "RayIoU@1" in out.output and "F-score" in out.output and "vehicle (2)" in out.output
    saved = json.loads((tmp_path / "e.json").read_text())
    assert saved["frames_matched"] == 3 and saved["mask"] == "mask_camera"
    assert f"{100 * saved['occ3d']['miou']:.2f}" in out.output
    own = runner.invoke(app, ["eval", truth_root, truth_root, "--field", "--no-rays", "--mask", "none"],
                        env={"COLUMNS": "160"})
    assert own.exit_code == 0, own.output
    assert "100.00" in own.output and "RayIoU@1" not in own.output
