"""Sensor metadata on copies of the shared synthetic log: the image match tolerance, the ego's motion between
sweep and image, unsafe file names, and a dataset whose log cannot be found (nuplan_occ.sensors)."""

import shutil
import sqlite3

import numpy as np
import pytest

from nuplan_occ.geometry import invert_transform
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.sensors import IMAGE_TOLERANCE_US, add_sensors, camera_to_lidar, frame_sensor_rows
from nuplan_occ.storage.sensors import frame_sensors
from tools_world import LOG, small_scene, write_dataset


@pytest.fixture
def shifted(synthetic_root, tmp_path):
    """A copy of the log's DB whose CAM_F0 keeps only its first image (taken at the first sweep), CAM_B0
    images are 30 ms late, and CAM_L0 images are named outside sensor_blobs."""
    db = next((synthetic_root / "nuplan-v1.1" / "splits" / "mini").glob("*.db"))
    copy = tmp_path / db.name
    shutil.copy(db, copy)
    with sqlite3.connect(copy) as con:
        def shift(channel: str, sql: str, *args) -> None:
            con.execute(f"UPDATE image SET {sql} WHERE camera_token = (SELECT token FROM camera WHERE channel = ?)",
                        (*args, channel))
        con.execute("DELETE FROM image WHERE camera_token = (SELECT token FROM camera WHERE channel = 'CAM_F0') "
                    "AND timestamp > (SELECT min(timestamp) FROM image)")
        shift("CAM_B0", "timestamp = timestamp + ?", 30_000)
        shift("CAM_L0", "filename_jpg = '../../etc/' || filename_jpg")
    return copy, synthetic_root / "nuplan-v1.1" / "sensor_blobs"


def test_images_match_within_the_tolerance_and_carry_the_ego_motion(shifted):
    db, blobs = shifted
    with NuplanLog(db, blobs) as log:
        frame = log.frames[4]  # 200 ms after the first sweep: CAM_F0's only image is too early
        assert frame.timestamp_us - log.frames[0].timestamp_us > IMAGE_TOLERANCE_US
        table = frame_sensor_rows(log, [(frame.token, frame.timestamp_us)], frame.scene_token, "blobs")
        sensors = frame_sensors(table.to_pylist())
        later = invert_transform(log.ego_pose_at(frame.timestamp_us)) @ log.ego_pose_at(frame.timestamp_us + 30_000)
        lidar_to_ego = log.lidar.T_ego_from_lidar
    cams = sensors["cameras"]
    assert len(cams) == 8 and sensors["lidar_filename"] == frame.filename
    # no image within 50 ms: none; named outside sensor_blobs: none (never opened); the others matched
    for channel in ("CAM_F0", "CAM_L0"):
        assert cams[channel]["image_path"] is None and cams[channel]["image_timestamp_us"] is None
    assert cams["CAM_R0"]["image_timestamp_us"] == frame.timestamp_us
    assert cams["CAM_R0"]["image_path"] == f"blobs/{cams['CAM_R0']['image_filename']}"
    assert np.allclose(cams["CAM_R0"]["image_ego_to_frame_ego"], np.eye(4))
    # 30 ms late: matched, with the ego's motion over those 30 ms (it drives: a visible translation)
    back = cams["CAM_B0"]
    assert back["image_timestamp_us"] == frame.timestamp_us + 30_000
    assert np.allclose(back["image_ego_to_frame_ego"], later) and np.linalg.norm(later[:3, 3]) > 0.05
    expected = invert_transform(lidar_to_ego) @ later @ back["camera_to_ego"]
    assert np.allclose(camera_to_lidar(back, lidar_to_ego), expected)


def test_a_log_that_cannot_be_found_is_named_and_nothing_is_written(synthetic_root, tmp_path):
    write_dataset(tmp_path / "ds", [{"semantics": small_scene(0)}])
    summary = add_sensors(str(tmp_path / "ds"), synthetic_root)
    assert summary["scenes"] == 0 and len(summary["problems"]) == 1 and LOG in summary["problems"][0]
    assert not (tmp_path / "ds" / "sensors").exists()


def test_cli_sensors_names_the_missing_log_and_exits_1(synthetic_root, tmp_path):
    from typer.testing import CliRunner

    from nuplan_occ.cli import app

    write_dataset(tmp_path / "ds", [{"semantics": small_scene(0)}])
    result = CliRunner().invoke(app, ["sensors", str(tmp_path / "ds"), str(synthetic_root)])
    assert result.exit_code == 1
    assert f"log {LOG}: " in result.output and "no DB for log" in result.output
