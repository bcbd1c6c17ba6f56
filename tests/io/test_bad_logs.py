"""Bad nuPlan input, one fault per test on a copy of the shared synthetic log: every case fails only
what it touches, with one line naming the file, or is dropped and counted; nothing goes silently wrong."""

from __future__ import annotations

import hashlib
import logging
import re
import shutil
import sqlite3
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from nuplan_occ.io.errors import DatabaseError, MissingBlobError, PointCloudError
from nuplan_occ.io.pcd import MAX_POINTS, encode_pcd, read_pcd
from nuplan_occ.io.reader import POSE_EDGE_LIMIT_US, NuplanLog, open_log
from nuplan_occ.io.types import PointCloud
from nuplan_occ.pipeline.build import plan_tasks
from nuplan_occ.stages import load

from pipeline_helpers import build_params


@dataclass
class Copy:
    """A private copy of the synthetic data root, with its DB, blob folder and maps folder."""

    root: Path
    db: Path
    blobs: Path
    maps: Path

    def sql(self, *statements: str, params: tuple = ()) -> None:
        db = sqlite3.connect(self.db)
        with db:
            for statement in statements:
                db.execute(statement, params)
        db.close()

    def frames(self) -> list:
        with NuplanLog(self.db, self.blobs) as log:
            return list(log.frames)

    def tasks(self) -> list:
        return plan_tasks([self.db], self.root, self.maps, str(self.root / "out"), self.root / "work", build_params())

    def load_scene(self, scene_name: str):
        """The load stage's SceneData of one scene (default load params)."""
        task = next(t for t in self.tasks() if t.scene_name == scene_name)
        return load.run({"task": task}, load.LoadParams())["scene"]

    def blob(self, frame) -> Path:
        return self.blobs / frame.filename


@pytest.fixture
def copy(synthetic_root, tmp_path) -> Copy:
    root = tmp_path / "data"
    shutil.copytree(synthetic_root, root)
    return Copy(root, next((root / "nuplan-v1.1" / "splits" / "mini").glob("*.db")),
                root / "nuplan-v1.1" / "sensor_blobs", root / "maps")


def _sweeps(scene) -> dict[str, object]:
    return {sweep.token: sweep for sweep in scene.sweeps}


def _one_line(message: str) -> None:
    assert message and "\n" not in message and "Traceback" not in message


def _rewrite(path: Path, change) -> PointCloud:
    """Apply `change` to a copy of the blob's cloud (lidar frame), write it back; the original cloud."""
    cloud = read_pcd(path.read_bytes(), str(path))
    damaged = PointCloud(cloud.xyz.copy(), cloud.intensity, cloud.ring, cloud.lidar_info, "lidar")
    change(damaged.xyz)
    path.write_bytes(encode_pcd(damaged))
    return cloud


# ------------------------------------------------------------------ 1. values that used to crash the build
def test_non_finite_and_far_points_are_dropped_and_counted(copy):
    frames = copy.frames()
    target = frames[6]  # scene-0001

    def damage(xyz):
        xyz[:100] = np.nan
        xyz[100:150] = np.inf
        xyz[150:150 + len(xyz) // 100] = [10_000.0, 0.0, 0.0]  # 1 % of the points at 10 km
    original = _rewrite(copy.blob(target), damage)
    sweep = _sweeps(copy.load_scene("scene-0001"))[target.token]
    assert sweep.failure == "" and sweep.dropped_points == 150 + len(original) // 100
    xyz = sweep.xyz
    assert len(xyz) == len(original) - sweep.dropped_points and np.isfinite(xyz).all()
    assert np.linalg.norm(xyz, axis=1).max() < 300.0


def test_null_ego_pose_value_drops_the_row_and_keeps_the_frames(copy):
    frames = copy.frames()
    db = sqlite3.connect(copy.db)
    (rows,) = db.execute("SELECT count(*) FROM ego_pose").fetchone()
    db.close()
    copy.sql("UPDATE ego_pose SET x = NULL WHERE rowid = 40", "UPDATE ego_pose SET qw = 'abc' WHERE rowid = 41")
    with NuplanLog(copy.db, copy.blobs) as log:
        assert len(log.ego_poses) == rows - 2
        assert any("2 of" in note and "ego_pose rows dropped" in note for note in log.notes)
        poses = [log.frame_pose(frame) for frame in frames]
    assert all(np.isfinite(pose).all() for pose in poses)


def test_non_finite_ego_poses_fail_only_the_frames_they_cover(copy):
    frames = copy.frames()
    target = frames[6]  # scene-0001 holds frames 5-9; 6 and 8 are its output frames
    copy.sql("UPDATE ego_pose SET x = 1e999 WHERE timestamp BETWEEN ? AND ?",
             params=(target.timestamp_us - 60_000, target.timestamp_us + 60_000))
    scene = copy.load_scene("scene-0001")
    sweeps = _sweeps(scene)
    for frame in frames[5:8]:  # inside the 130 ms without a usable row
        failed = sweeps[frame.token]
        assert not failed.has_cloud and str(copy.db) in failed.failure and "ms apart (limit 100 ms)" in failed.failure
        _one_line(failed.failure)
        assert np.isfinite(failed.logged_pose).all()  # a stand-in for registration, never a NaN
    assert sweeps[frames[8].token].has_cloud and sweeps[frames[8].token].failure == ""


def test_pose_rows_missing_at_the_end_fail_those_frames_instead_of_extrapolating(copy):
    frames = copy.frames()
    cut = frames[-4].timestamp_us  # rows of the last 0.15 s removed
    copy.sql("DELETE FROM ego_pose WHERE timestamp > ?", params=(cut,))
    scene = copy.load_scene("scene-0004")
    sweeps = _sweeps(scene)
    for frame in frames[-4:]:
        beyond = frame.timestamp_us - cut
        sweep = sweeps[frame.token]
        if beyond <= POSE_EDGE_LIMIT_US:
            assert sweep.failure == ""
        else:
            assert "after the last usable ego_pose row" in sweep.failure and not sweep.has_cloud
    assert sum(not s.has_cloud for s in scene.sweeps) == sum(f.timestamp_us - cut > POSE_EDGE_LIMIT_US for f in frames)


# ------------------------------------------------------------------ 2. inputs stay inside the data root
def test_filenames_leaving_the_data_root_are_never_opened(copy, tmp_path):
    frames = copy.frames()
    outside = tmp_path / "outside" / "secret.pcd"
    outside.parent.mkdir()
    shutil.copy(copy.blob(frames[5]), outside)  # a valid PCD: the old reader published it as an "ok" frame
    climbing = "../" * (len(copy.blobs.parts) + 2) + str(outside).lstrip("/")
    copy.sql("UPDATE lidar_pc SET filename = ? WHERE token = ?", params=(climbing, bytes.fromhex(frames[6].token)))
    copy.sql("UPDATE lidar_pc SET filename = ? WHERE token = ?", params=(str(outside), bytes.fromhex(frames[7].token)))
    before = outside.stat().st_atime_ns
    sweeps = _sweeps(copy.load_scene("scene-0001"))
    for frame in (frames[6], frames[7]):
        failure = sweeps[frame.token].failure
        assert "leaves the sensor_blobs folder" in failure and "secret" not in failure and "outside" not in failure
        assert not sweeps[frame.token].has_cloud
        _one_line(failure)
    assert sweeps[frames[8].token].has_cloud
    assert outside.stat().st_atime_ns == before


# ------------------------------------------------------------------ 3. silent wrongs made loud
def test_duplicate_timestamps_keep_chain_order_and_flag_the_repeat(copy):
    frames = copy.frames()
    first, second = frames[6], frames[7]
    copy.sql("UPDATE lidar_pc SET timestamp = ? WHERE token = ?",
             params=(first.timestamp_us, bytes.fromhex(second.token)))
    renamed = "00" + first.token  # sorts before the second by token: chain order must decide
    copy.sql("UPDATE lidar_pc SET token = ? WHERE token = ?", params=(bytes.fromhex(renamed), bytes.fromhex(first.token)))
    copy.sql("UPDATE lidar_pc SET prev_token = ? WHERE token = ?", params=(bytes.fromhex(renamed), bytes.fromhex(second.token)))
    with NuplanLog(copy.db, copy.blobs) as log:
        order = [f.token for f in log.frames]
        assert order.index(renamed) + 1 == order.index(second.token)
        assert log.frames[order.index(renamed)].problem == ""
        assert "repeats the timestamp" in log.frames[order.index(second.token)].problem
    copy.sql("UPDATE lidar_pc SET prev_token = NULL WHERE token = ?", params=(bytes.fromhex(second.token),))
    copy.sql("UPDATE lidar_pc SET token = ? WHERE token = ?", params=(bytes.fromhex("ff" + second.token),
                                                                      bytes.fromhex(second.token)))
    with NuplanLog(copy.db, copy.blobs) as log:  # no chain: token order, the same on every read
        order = [(f.token, bool(f.problem)) for f in log.frames]
        assert order[order.index((renamed, False)) + 1] == ("ff" + second.token, True)
    sweeps = _sweeps(copy.load_scene("scene-0001"))
    assert sweeps[renamed].has_cloud
    assert "repeats the timestamp" in sweeps["ff" + second.token].failure


@pytest.mark.parametrize("kind", ["empty", "all_zero"])
def test_empty_or_all_zero_pcd_fails_its_frame(copy, kind):
    frames = copy.frames()
    target = frames[6]
    path = copy.blob(target)
    if kind == "empty":
        path.write_bytes(encode_pcd(PointCloud(np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.int16),
                                               np.zeros(0, np.int8), "lidar")))
    else:
        _rewrite(path, lambda xyz: xyz.fill(0.0))
    sweeps = _sweeps(copy.load_scene("scene-0001"))
    failure = sweeps[target.token].failure
    assert str(path) in failure and ("no points" in failure or "only 0 of" in failure)
    assert not sweeps[target.token].has_cloud and sweeps[frames[8].token].has_cloud


@pytest.mark.parametrize("remove", ["map_folder", "version_folder"])
def test_missing_map_warns_once_per_log_and_is_carried_to_the_scene(copy, caplog, remove):
    folder = copy.maps / "us-nv-las-vegas-strip"
    shutil.rmtree(folder if remove == "map_folder" else folder / "9.15.1915")
    with caplog.at_level(logging.WARNING, logger="nuplan_occ.build"):
        tasks = copy.tasks()
    warnings = [r.getMessage() for r in caplog.records if "no usable map" in r.getMessage()]
    assert len(warnings) == 1 and str(folder) in warnings[0] and len(tasks) == 5
    scene = copy.load_scene("scene-0001")
    assert scene.map_path is None and str(folder) in scene.map_problem and "other" in scene.map_problem


# ------------------------------------------------------------------ 4. messages
def test_zero_byte_db_says_it_is_empty(copy):
    copy.db.write_bytes(b"")
    with pytest.raises(DatabaseError, match=r"empty \(0 bytes\)") as err:
        NuplanLog(copy.db)
    assert err.value.path == str(copy.db)


def test_null_box_size_fails_only_its_frame_naming_table_token_and_column(copy):
    frames = copy.frames()
    target = frames[6]
    db = sqlite3.connect(copy.db)
    (box,) = db.execute("SELECT token FROM lidar_box WHERE lidar_pc_token = ? LIMIT 1",
                        (bytes.fromhex(target.token),)).fetchone()
    db.close()
    copy.sql("UPDATE lidar_box SET width = NULL WHERE token = ?", params=(box,))
    scene = copy.load_scene("scene-0001")
    failed = [s for s in scene.sweeps if s.failure]
    assert [s.token for s in failed] == [target.token]
    assert f"table lidar_box, token {box.hex()}, column width: NULL" in failed[0].failure
    assert str(copy.db) in failed[0].failure
    _one_line(failed[0].failure)


def test_scene_without_blobs_fails_early_naming_the_folder_and_count(copy):
    frames = copy.frames()
    with NuplanLog(copy.db, copy.blobs) as log:
        scene = next(s for s in log.scenes if s.name == "scene-0002")
        own = log.frames_of_scene(scene.token)
    for frame in own:
        copy.blob(frame).unlink()
    with pytest.raises(MissingBlobError) as err:
        copy.load_scene("scene-0002")
    folder = copy.blob(own[0]).parent
    assert err.value.path == str(folder)
    assert f"{len([f for f in own if f.index % 2 == 0])} of the" in err.value.problem
    _one_line(str(err.value))
    assert len(frames) > len(own) and copy.load_scene("scene-0001").sweeps  # the other scenes still load


def test_oversized_point_count_is_refused_before_allocating(copy):
    path = copy.blob(copy.frames()[0])
    header = path.read_bytes().split(b"DATA binary\n")[0]
    huge = re.sub(rb"POINTS \d+", b"POINTS 99999999999", header)
    with pytest.raises(PointCloudError, match=f"exceeds the {MAX_POINTS} points"):
        read_pcd(huge + b"DATA binary\n" + b"\x00" * 64, str(path))


# ------------------------------------------------------------------ 5. opening and box queries leave the DB as it is
def test_loading_scenes_never_writes_the_users_db_and_reuses_one_open_log(copy):
    digest = hashlib.sha256(copy.db.read_bytes()).hexdigest()
    first = copy.load_scene("scene-0001")
    log = open_log(str(copy.db), str(copy.blobs))
    second = copy.load_scene("scene-0002")
    assert open_log(str(copy.db), str(copy.blobs)) is log
    with NuplanLog(copy.db, copy.blobs) as fresh:
        for sweep in [*first.sweeps, *second.sweeps]:
            frame = next(f for f in fresh.frames if f.token == sweep.token)
            assert sorted(sweep.boxes_global.tokens) == sorted(fresh.boxes(frame).tokens)
    assert hashlib.sha256(copy.db.read_bytes()).hexdigest() == digest
    db = sqlite3.connect(copy.db)
    assert db.execute("SELECT count(*) FROM sqlite_master WHERE type = 'index' AND sql IS NOT NULL").fetchone() == (0,)
    db.close()
