"""Our build -> `export --format uniscene` -> `import-release` back, and a LiDAR-frame release converted
with the log's extrinsic, both with the nuPlan DBs of the shared synthetic build (tests/pipeline/conftest.py)."""

import numpy as np
from typer.testing import CliRunner

from nuplan_occ.cli import app
from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.release.regrid import resample
from nuplan_occ.storage import read_manifest, validate_dataset
from nuplan_occ.synth.lidar import T_EGO_FROM_LIDAR


def cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_uniscene_export_imported_back_equals_the_build(reference_build, synthetic_root, tmp_path):
    # --frame ego: the build's own frame (uniscene's default is the LiDAR frame, a nearest-voxel resampling)
    assert cli("export", reference_build, tmp_path / "exp", "--format", "uniscene", "--frame", "ego").exit_code == 0
    result = cli("import-release", tmp_path / "exp", tmp_path / "back", "--labels", "nuplan-occ",
                 "--logs-root", synthetic_root)
    assert result.exit_code == 0, result.output
    built, back = open_dataset(str(reference_build)), open_dataset(str(tmp_path / "back"))
    assert len(back) == len(built) > 0
    for i in range(len(built)):
        ours = built.get(i, keys=("semantics",))
        imported = back.get(back.index_of_token(ours["token"]), keys=("semantics",))
        np.testing.assert_array_equal(imported["semantics"], ours["semantics"])
        for name in ("log_name", "scene_token", "frame_index", "timestamp_us"):
            assert imported[name] == ours[name], name
        # the logged pose, not our refined one: close to it, never NaN
        assert np.abs(imported["ego_to_global"][:3, 3] - ours["ego_to_global"][:3, 3]).max() < 1.0
    manifest = read_manifest(str(tmp_path / "back"))
    assert manifest["release_log_matched"].to_pylist() == [True] * len(built)
    assert manifest["ego_speed"].null_count == 0
    assert validate_dataset(str(tmp_path / "back")) == []


def test_lidar_frame_release_is_converted_with_the_logs_extrinsic(reference_build, synthetic_root, tmp_path):
    built = open_dataset(str(reference_build))
    frame = built.get(0, keys=("semantics",))
    ego = frame["semantics"]
    lidar = resample(ego, DEFAULT_GRID, DEFAULT_GRID, T_EGO_FROM_LIDAR)  # the release's grid in the LiDAR frame
    target = tmp_path / "rel" / "dense_voxels_with_semantic" / frame["scene_token"]
    target.mkdir(parents=True)
    voxels = np.argwhere(lidar > 0)
    np.savez_compressed(target / f"{frame['token']}.npz", occ=np.concatenate([voxels, lidar[tuple(voxels.T)][:, None]], 1))
    for logs in (["--logs-root", synthetic_root], []):
        out = tmp_path / f"out{len(logs)}"
        result = cli("import-release", tmp_path / "rel", out, "--frame", "lidar", "--labels", "nuplan-occ", *logs)
        assert result.exit_code == 0, result.output
        imported = open_dataset(str(out))[0]["semantics"]
        agree = np.count_nonzero((imported == ego) & (ego > 0)) / np.count_nonzero(ego)
        kept = read_manifest(str(out))["release_frame"].to_pylist() == ["lidar"]
        if logs:  # back in the ego frame: two nearest-voxel resamplings away from the build
            assert not kept and agree > 0.8
        else:  # no extrinsic: kept where the LiDAR frame puts it (1.5 m behind, 1.6 m below), and marked
            assert kept and agree < 0.2
