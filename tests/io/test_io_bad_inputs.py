"""Each bad input gives its specific exception, naming the offending file (issue 2, item 5)."""

from __future__ import annotations

import os
import pickle
import sqlite3

import numpy as np
import pytest

from nuplan_io_logfactory import build_log, write_built
from nuplan_occ.io.errors import (
    DatabaseError, MissingBlobError, NuplanFormatError, PointCloudError, SchemaError, UnsafePickleError,
)
from nuplan_occ.io.reader import NuplanLog

TOKEN_COLUMNS = {
    "log": ("token",), "category": ("token",), "lidar": ("token", "log_token"), "camera": ("token", "log_token"),
    "ego_pose": ("token", "log_token"), "scene": ("token", "log_token", "goal_ego_pose_token"),
    "lidar_pc": ("token", "next_token", "prev_token", "ego_pose_token", "lidar_token", "scene_token"),
    "image": ("token", "next_token", "prev_token", "ego_pose_token", "camera_token"),
    "track": ("token", "category_token"),
    "lidar_box": ("token", "lidar_pc_token", "track_token", "next_token", "prev_token"),
}


@pytest.fixture(scope="module")
def built():
    return build_log(seed=2, n_frames=5)


@pytest.fixture
def db_path(built, tmp_path):
    return write_built(built, tmp_path)


def _sql(db_path, *statements):
    db = sqlite3.connect(db_path)
    with db:
        for statement in statements:
            db.execute(statement)
    db.close()


def _names(exc: NuplanFormatError, path) -> None:
    assert exc.path == str(path) and str(path) in str(exc)


def _snapshot(log: NuplanLog) -> list:
    """Frame times, box centres (sorted by token) and point counts: what must survive harmless DB changes."""
    out = []
    for frame in log.frames:
        boxes = log.boxes(frame)
        order = np.argsort(boxes.tokens)
        out.append((frame.timestamp_us, boxes.centers[order].round(9).tolist(), sorted(boxes.categories),
                    len(log.load_points(frame))))
    return out


def test_missing_sensor_blobs_folder(built, tmp_path):
    db_path = write_built(built, tmp_path, with_points=False)
    with NuplanLog(db_path) as log, pytest.raises(MissingBlobError, match="sensor_blobs folder") as err:
        log.load_points(log.frames[0])
    _names(err.value, tmp_path / "nuplan-v1.1" / "sensor_blobs")


def test_missing_log_folder_in_sensor_blobs(built, tmp_path):
    db_path = write_built(built, tmp_path, with_points=False)
    (tmp_path / "nuplan-v1.1" / "sensor_blobs").mkdir()
    with NuplanLog(db_path) as log, pytest.raises(MissingBlobError, match="of this log") as err:
        log.load_points(log.frames[0])
    _names(err.value, tmp_path / "nuplan-v1.1" / "sensor_blobs" / built.content.meta.logfile)


def test_missing_blob_file(db_path):
    with NuplanLog(db_path) as log:
        path = log.blob_path(log.frames[1])
        path.unlink()
        with pytest.raises(MissingBlobError, match="missing") as err:
            log.load_points(log.frames[1])
        _names(err.value, path)
        assert len(log.load_points(log.frames[0])) > 0


@pytest.mark.parametrize("damage, message", [
    (lambda b: b[:-7], "truncated"),
    (lambda b: b[:40], "no DATA line"),
    (lambda b: bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8)), "not ASCII|no DATA"),
    (lambda b: b.replace(b"DATA binary", b"DATA ascii"), "unsupported PCD DATA ascii"),
    (lambda b: b.replace(b"DATA binary", b"DATA binary_compressed"), "unsupported PCD DATA"),
    (lambda b: b.replace(b"COUNT 1 1 1 1 1 1", b"COUNT 1 1 1 1 1 3"), "COUNT"),
    (lambda b: b.replace(b"TYPE F F F F F F", b"TYPE F F F F F X"), "unsupported PCD field"),
])
def test_corrupt_pcd(db_path, damage, message):
    with NuplanLog(db_path) as log:
        path = log.blob_path(log.frames[0])
        path.write_bytes(damage(path.read_bytes()))
        with pytest.raises(PointCloudError, match=message) as err:
            log.load_points(log.frames[0])
        _names(err.value, path)


def test_db_without_merged_point_cloud_row(db_path):
    _sql(db_path, "UPDATE lidar SET channel = 'LIDAR_TOP'")
    with pytest.raises(SchemaError, match="MergedPointCloud") as err:
        NuplanLog(db_path)
    _names(err.value, db_path)


def test_db_with_two_merged_point_cloud_rows(db_path):
    _sql(db_path, "INSERT INTO lidar SELECT x'0102', log_token, channel, model, translation, rotation FROM lidar")
    with pytest.raises(SchemaError, match="found 2"):
        NuplanLog(db_path)


def test_unknown_category(db_path):
    _sql(db_path, "UPDATE category SET name = 'car' WHERE name = 'vehicle'")
    with NuplanLog(db_path) as log:
        assert len(log.load_points(log.frames[0])) > 0  # poses and points stay usable
        with pytest.raises(SchemaError, match="unknown category 'car'") as err:
            log.boxes(log.frames[0])
        _names(err.value, db_path)
        with pytest.raises(SchemaError):
            log.box_counts()


def test_null_chain_ends_everywhere(db_path):
    with NuplanLog(db_path) as log:
        before = _snapshot(log)
    _sql(db_path, "UPDATE lidar_pc SET next_token = NULL, prev_token = NULL",
         "UPDATE lidar_box SET next_token = NULL, prev_token = x''", "UPDATE scene SET goal_ego_pose_token = NULL")
    with NuplanLog(db_path) as log:
        assert all(f.next_token is None and f.prev_token is None for f in log.frames)
        assert all(s.goal_ego_pose_token is None for s in log.scenes)
        assert _snapshot(log) == before


def test_extra_columns(db_path):
    with NuplanLog(db_path) as log:
        before = _snapshot(log)
    statements = []
    for table in ("lidar_box", "lidar_pc", "ego_pose", "track", "lidar"):
        statements += [f"ALTER TABLE {table} RENAME TO {table}_old",
                       f"CREATE TABLE {table} AS SELECT 0.5 AS roll, 'x' AS health, * FROM {table}_old",
                       f"DROP TABLE {table}_old"]
    statements += ["ALTER TABLE log ADD COLUMN vehicle_type TEXT", "ALTER TABLE lidar ADD COLUMN max_nbr_points INT"]
    _sql(db_path, *statements)
    with NuplanLog(db_path) as log:
        assert _snapshot(log) == before


def test_four_byte_tokens(db_path):
    with NuplanLog(db_path) as log:
        before = _snapshot(log)
    _sql(db_path, *[f"UPDATE {table} SET {col} = substr({col}, 1, 4)"
                    for table, cols in TOKEN_COLUMNS.items() for col in cols])
    with NuplanLog(db_path) as log:
        assert all(len(f.token) == 8 for f in log.frames) and len(log.meta.token) == 8
        assert _snapshot(log) == before
        assert log.frames[0].next_token == log.frames[1].token


def test_text_token_is_refused(db_path):
    _sql(db_path, "UPDATE lidar_pc SET token = hex(token)")
    with pytest.raises(SchemaError, match="lidar_pc.token holds a str token") as err:
        NuplanLog(db_path)
    _names(err.value, db_path)


@pytest.mark.parametrize("statement, message", [
    ("ALTER TABLE lidar_box DROP COLUMN yaw", "lidar_box lacks column"),
    ("DROP TABLE ego_pose", "table ego_pose is missing"),
    ("DELETE FROM log", "no row"),
])
def test_missing_table_column_or_row(db_path, statement, message):
    _sql(db_path, statement)
    with pytest.raises(SchemaError, match=message) as err:
        NuplanLog(db_path)
    _names(err.value, db_path)


def test_not_a_database(tmp_path):
    bad = tmp_path / "bad.db"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(DatabaseError) as err:
        NuplanLog(bad)
    _names(err.value, bad)
    with pytest.raises(DatabaseError, match="not found"):
        NuplanLog(tmp_path / "absent.db")


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_calibration_pickle_in_db_is_refused(db_path, tmp_path):
    marker = tmp_path / "pwned"
    db = sqlite3.connect(db_path)
    with db:
        db.execute("UPDATE lidar SET translation = ?", (pickle.dumps(_Payload(marker)),))
    db.close()
    with pytest.raises(UnsafePickleError, match="lidar.translation") as err:
        NuplanLog(db_path)
    _names(err.value, db_path)
    assert not marker.exists()
