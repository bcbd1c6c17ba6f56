"""import-release on release-format fixtures (tests/release/release_fixtures.py) with known truth."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from nuplan_occ.cli import app
from nuplan_occ.dataset import open_dataset
from nuplan_occ.release.importer import ImportOptions, import_release
from nuplan_occ.stats import dataset_stats
from nuplan_occ.storage import read_manifest, read_metadata, validate_dataset
from nuplan_occ.torch import OccupancyDataset
from release_fixtures import truth_frames, write_dense, write_sparse

FOLDER = "0123456789abcdef"


def cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def truth():
    return truth_frames(2)


@pytest.mark.parametrize("layout", ["sparse4", "sparse2", "dense"])
@pytest.mark.parametrize("z_min", [-3.0, -5.0])
def test_import_equals_truth_in_every_layout_and_z_convention(truth, layout, z_min, tmp_path):
    src = tmp_path / "release"
    if layout == "dense":
        write_dense(src, truth, z_min=z_min)
    else:
        write_sparse(src, FOLDER, truth, columns=int(layout[-1]), z_min=z_min)
    out = tmp_path / "out"
    result = cli("import-release", src, out, "--z-min", z_min)  # layout auto-detected
    assert result.exit_code == 0, result.output
    ds = open_dataset(str(out))
    assert len(ds) == len(truth)
    for i in range(len(ds)):
        frame = ds[i]
        np.testing.assert_array_equal(frame["semantics"], truth[frame["token"]])
        # without the logs nothing but the token is known, and nothing is invented
        assert frame["log_name"] is None and frame["scene_token"] is None and frame["timestamp_us"] is None
        assert np.isnan(frame["ego_to_global"]).all()
    manifest = read_manifest(str(out))
    assert set(manifest["release_layout"].to_pylist()) == {layout}
    assert set(manifest["release_frame"].to_pylist()) == {"ego"}
    release = read_metadata(str(out))["release"]
    assert release["source_z_range_m"] == [z_min, z_min + 8]
    assert release["label_map"]["name"] == ("uniscene" if layout == "dense" else "raw-sparse")
    assert validate_dataset(str(out)) == []
    assert dataset_stats(str(out))["frames"]["ok"] == len(truth)
    clips = OccupancyDataset(str(out), clip_len=1)
    assert len(clips) == len(truth) and clips[0]["frame_index"].tolist() == [-1]


def test_malformed_files_fail_their_frame_and_a_rerun_skips_the_done_ones(truth, tmp_path):
    src = tmp_path / "release"
    folder = write_sparse(src, FOLDER, truth, columns=4)
    write_sparse(src, FOLDER, {"00ff00ff00ff00ff": next(iter(truth.values()))}, columns=2)  # mixed layouts: auto
    (folder / "aaaaaaaaaaaaaaa1.npz").write_bytes(b"not a zip")
    np.savez_compressed(folder / "aaaaaaaaaaaaaaa2.npz", grid=np.zeros(3))
    np.savez_compressed(folder / "aaaaaaaaaaaaaaa3.npz", occ=np.array([[400, 0, 0, 1]]))
    np.savez_compressed(folder / "aaaaaaaaaaaaaaa4.npz", occ=np.zeros((3, 3), dtype=np.int32))
    out = tmp_path / "out"
    result = cli("import-release", src, out)
    assert result.exit_code == 0, result.output
    rows = {r["token"]: r for r in read_manifest(str(out)).to_pylist()}
    assert {t for t, r in rows.items() if r["status"] == "ok"} == set(truth) | {"00ff00ff00ff00ff"}
    assert rows["00ff00ff00ff00ff"]["release_layout"] == "sparse2"
    reasons = {t: r["failure_reason"] for t, r in rows.items() if r["status"] == "failed"}
    assert reasons == {
        "aaaaaaaaaaaaaaa1": "aaaaaaaaaaaaaaa1.npz: not an .npz archive (starts with b'not ')",
        "aaaaaaaaaaaaaaa2": "aaaaaaaaaaaaaaa2.npz: no 'occ' array (holds ['grid'])",
        "aaaaaaaaaaaaaaa3": "aaaaaaaaaaaaaaa3.npz: 1 voxel indices outside the (400, 400, 32) grid",
        "aaaaaaaaaaaaaaa4": "aaaaaaaaaaaaaaa4.npz: occ has shape [3, 3], expected [N, 4] or [N, 2]",
    }
    assert validate_dataset(str(out)) == []
    identity = ["token", "status", "failure_reason", "semantics_crc32"]
    before = read_manifest(str(out)).select(identity)
    again = cli("import-release", src, out)
    assert again.exit_code == 0 and "skipped" in again.output
    assert read_manifest(str(out)).select(identity).equals(before)  # failed ones retried, ok ones skipped
    other = cli("import-release", src, out, "--z-min", "-5")
    assert other.exit_code == 1 and "import into a new OUT" in other.output


def test_label_ids_outside_the_map_stop_with_one_line_naming_the_file(truth, tmp_path):
    src = tmp_path / "release"
    folder = write_sparse(src, FOLDER, truth, columns=4)
    bad = folder / "ffffffffffffffff.npz"  # sorted last: the frames before it are kept
    np.savez_compressed(bad, occ=np.array([[1, 2, 3, 1], [4, 5, 6, 3]], dtype=np.int32))
    out = tmp_path / "out"
    result = cli("import-release", src, out)
    assert result.exit_code == 1
    lines = [line for line in result.output.splitlines() if line.startswith("error")]  # the rest is progress
    assert len(lines) == 1 and f"error {bad}: " in lines[0]
    assert "label ids [3] are not in label map 'raw-sparse'" in lines[0]
    assert set(read_manifest(str(out))["token"].to_pylist()) == set(truth)


def test_bad_options_stop_with_one_line(truth, tmp_path):
    src = tmp_path / "release"
    write_dense(src, truth)
    (tmp_path / "no_logs").mkdir()
    for args, message in ((["--logs-root", tmp_path / "no_logs"], "no *.db log files found"),
                          (["--labels", "nope"], "neither a label map name"),
                          (["--layout", "sparse4"], "no dense_voxels_with_semantic/")):
        result = cli("import-release", src, tmp_path / "out", *args)
        assert result.exit_code == 1 and message in result.output, result.output
    assert not (tmp_path / "out" / "manifest.parquet").exists()


def test_label_map_file_flat_order_and_kept_lidar_frame(truth, tmp_path):
    src = tmp_path / "release"
    target = src / "dense_voxels_with_semantic" / FOLDER
    target.mkdir(parents=True)
    token, semantics = next(iter(truth.items()))
    voxels = np.argwhere(semantics > 0)
    flat_zyx = np.ravel_multi_index(tuple(voxels[:, ::-1].T), semantics.shape[::-1])  # x fastest
    np.savez_compressed(target / f"{token}.npz", occ=np.stack([flat_zyx, 100 + semantics[tuple(voxels.T)]], 1))
    label_file = tmp_path / "map.json"
    label_file.write_text(json.dumps({"name": "plus100", "classes": [
        {"id": 100 + i, "name": f"c{i}", "ours": i} for i in range(1, 9)]}))
    out = tmp_path / "out"
    result = cli("import-release", src, out, "--labels", label_file, "--flat-order", "zyx", "--frame", "lidar")
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(open_dataset(str(out))[0]["semantics"], semantics)
    # no logs, so no LiDAR extrinsic: the grid is kept in the LiDAR frame and marked so
    assert read_manifest(str(out))["release_frame"].to_pylist() == ["lidar"]
    assert read_metadata(str(out))["release"]["label_map"]["name"] == "plus100"


def test_eval_of_two_imports_and_the_side_by_side_picture(truth, tmp_path):
    changed = {t: s.copy() for t, s in truth.items()}
    for s in changed.values():
        s[s == 2] = 3  # every vehicle voxel becomes a bicycle
    write_dense(tmp_path / "a", truth)
    write_dense(tmp_path / "b", changed)
    assert cli("import-release", tmp_path / "a", tmp_path / "release").exit_code == 0
    assert cli("import-release", tmp_path / "b", tmp_path / "ours").exit_code == 0
    picture = tmp_path / "cmp.png"
    result = cli("eval", tmp_path / "release", tmp_path / "ours", "--mask", "none", "--json", tmp_path / "e.json",
                 "--picture", picture)
    assert result.exit_code == 0, result.output
    pooled = json.loads((tmp_path / "e.json").read_text())["pooled"]
    assert pooled["iou"] == 1.0 and pooled["per_class"]["2"] == 0.0 and pooled["per_class"]["4"] == 1.0
    bikes = sum(int((s == 3).sum()) for s in truth.values())
    assert pooled["per_class"]["3"] == pytest.approx(bikes / sum(int((s == 3).sum()) for s in changed.values()))
    assert picture.stat().st_size > 10_000 and "per frame" in result.output


def test_a_fixed_file_is_reimported_with_its_chunk_and_leaves_no_failed_row(tmp_path):
    truth = truth_frames(3, seed=1)
    bad_token, *good = sorted(truth)
    src = tmp_path / "release"
    folder = write_sparse(src, FOLDER, {t: truth[t] for t in good}, columns=4)
    (folder / f"{bad_token}.npz").write_bytes(b"not a zip")
    out = str(tmp_path / "out")
    options = ImportOptions(chunk_frames=2, commit_every_s=0.0)  # chunks [bad, good0], [good1], each committed
    first = import_release(src, out, options)
    assert (first.imported, first.failed) == (2, 1)
    rows = read_manifest(out).to_pylist()
    assert sorted(r["token"] for r in rows) == sorted(truth)  # every chunk's commit visible, no scene known
    shards = {r["token"]: r["shard"] for r in rows}
    assert shards[bad_token] == shards[good[0]] != shards[good[1]]

    write_sparse(src, FOLDER, {bad_token: truth[bad_token]}, columns=4)  # the file is fixed
    again = import_release(src, out, options)
    assert (again.imported, again.failed, again.skipped) == (2, 0, 1)  # its chunk redone whole, the other skipped
    rows = read_manifest(out).to_pylist()
    assert [r["token"] for r in rows] == sorted(truth) and {r["status"] for r in rows} == {"ok"}  # unknown keys: by token
    assert {r["token"]: r["shard"] for r in rows} == shards  # rewritten under the same shard keys
    ds = open_dataset(out)
    for token, semantics in truth.items():
        np.testing.assert_array_equal(ds[ds.index_of_token(token)]["semantics"], semantics)
    assert validate_dataset(out) == []
