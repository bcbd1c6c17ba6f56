"""Writer -> reader round trip on a hand-made log, frame chain and pose interpolation against ground truth."""

from __future__ import annotations

import pickle
import sqlite3

import numpy as np
import pytest

from nuplan_io_logfactory import POSE_PERIOD_US, T_EGO_FROM_LIDAR, build_log, true_pose, write_built
from nuplan_occ.geometry import invert_transform, transform_points, yaw_matrix
from nuplan_occ.io.errors import PoseGapError
from nuplan_occ.io.reader import POSE_EDGE_LIMIT_US, NuplanLog, points_to_ego, points_to_global, slerp
from nuplan_occ.io.types import NUPLAN_CATEGORIES


@pytest.fixture(scope="module")
def built():
    return build_log(seed=1)


@pytest.fixture(scope="module")
def db_path(built, tmp_path_factory):
    return write_built(built, tmp_path_factory.mktemp("data"))


def _inside(boxes, k, xyz, margin=1e-6):
    local = transform_points(boxes.box_from_frame()[k], xyz)
    return np.all(np.abs(local) <= boxes.sizes[k] / 2 + margin, axis=1)


def test_layout_and_records_round_trip(built, db_path):
    content = built.content
    assert db_path.name == f"{content.meta.logfile}.db" and db_path.parent.name == "mini"
    assert not [p for p in db_path.parent.iterdir() if p.name.endswith(".tmp")]
    with NuplanLog(db_path) as log:
        assert log.meta == content.meta
        assert log.sensor_root == db_path.parents[2] / "sensor_blobs"
        np.testing.assert_allclose(log.lidar.T_ego_from_lidar, T_EGO_FROM_LIDAR, atol=1e-12)
        (camera,) = log.cameras
        np.testing.assert_allclose(camera.K, content.cameras[0].K)
        np.testing.assert_allclose(camera.distortion, content.cameras[0].distortion)
        assert (camera.width, camera.height, camera.channel) == (1920, 1080, "CAM_F0")
        assert [s.name for s in log.scenes] == [f"scene-{i:04d}" for i in range(5)]
        assert log.scenes[2].roadblock_ids == ["102", "202"]
        times = [f.timestamp_us for f in log.frames]
        assert times == sorted(times) and [f.index for f in log.frames] == list(range(len(times)))
        assert log.frames[0].prev_token is None and log.frames[-1].next_token is None
        for a, b in zip(log.frames, log.frames[1:]):
            assert a.next_token == b.token and b.prev_token == a.token
        assert sum(len(log.frames_of_scene(s.token)) for s in log.scenes) == len(log.frames)
        assert {t.token: t.category for t in content.tracks} == {k: v.category for k, v in log.tracks.items()}
        assert len(log.ego_poses) == len(content.ego_poses)
        for k, want in enumerate(content.ego_poses):
            np.testing.assert_allclose(log.ego_poses.T_global_from_ego(k), want.T_global_from_ego, atol=1e-9)
            assert log.ego_poses.tokens[k] == want.token and log.ego_poses.timestamps_us[k] == want.timestamp_us
        images = sorted(content.images, key=lambda i: (i.timestamp_us, i.token))
        assert log.images.tokens.tolist() == [i.token for i in images]
        assert log.images.timestamps_us.tolist() == [i.timestamp_us for i in images]
        assert [f.decode() for f in log.images.filenames] == [i.filename_jpg for i in images]


def test_boxes_and_points_round_trip(built, db_path):
    with NuplanLog(db_path) as log:
        for frame in log.frames:
            want = built.content.boxes[frame.token]
            got = log.boxes(frame)
            order = [got.tokens.index(t) for t in want.tokens]
            got = got.subset(np.array(order))
            np.testing.assert_allclose(got.centers, want.centers, atol=1e-9)
            np.testing.assert_allclose(got.sizes, want.sizes)
            np.testing.assert_allclose(got.yaws, want.yaws)
            np.testing.assert_allclose(got.velocities, want.velocities)
            assert got.categories == want.categories and got.track_tokens == want.track_tokens
            cloud = log.load_points(frame)
            ref = built.clouds[frame.token]
            assert cloud.frame == "lidar"
            np.testing.assert_allclose(cloud.xyz, ref.xyz, atol=1e-4)  # stored as float32
            np.testing.assert_array_equal(cloud.ring, ref.ring)
            np.testing.assert_array_equal(cloud.lidar_info, ref.lidar_info)
            np.testing.assert_allclose(cloud.intensity, ref.intensity)


def test_frame_chain_points_land_in_their_boxes(built, db_path):
    """Points sampled inside global boxes, stored in the lidar frame, land in the same boxes in ego and global."""
    with NuplanLog(db_path) as log:
        for frame in log.frames:
            cloud = log.load_points(frame)
            owner = built.inside[frame.token]
            global_boxes, ego_boxes = log.boxes(frame, "global"), log.boxes(frame, "ego")
            in_global = points_to_global(cloud, log, frame)
            in_ego = points_to_ego(cloud, log)
            assert in_global.frame == "global" and in_ego.frame == "ego"
            for k_want, token in enumerate(built.content.boxes[frame.token].tokens):
                k = global_boxes.tokens.index(token)
                mine = owner == k_want
                assert _inside(global_boxes, k, in_global.xyz[mine], 1e-4).all()
                assert _inside(ego_boxes, k, in_ego.xyz[mine], 1e-4).all()
                assert not _inside(ego_boxes, k, in_ego.xyz[owner == -1], -0.05).any()
            ground = in_ego.xyz[owner == -1]
            np.testing.assert_allclose(ground[:, 2], 0.0, atol=1e-4)  # ground points were sampled at ego z = 0


def test_ego_pose_at_interpolates_between_rows_at_a_different_rate(db_path):
    with NuplanLog(db_path) as log:
        rows = log.ego_poses
        times = rows.timestamps_us
        for frame in log.frames:
            linked = rows.index_of(frame.ego_pose_token)
            assert times[linked] != frame.timestamp_us  # the link is not at frame time
            pose = log.frame_pose(frame)
            truth = true_pose(frame.timestamp_us)
            np.testing.assert_allclose(pose[:3, 3], truth[:3, 3], atol=1e-3)
            np.testing.assert_allclose(pose[:3, :3], truth[:3, :3], atol=1e-9)
            assert np.linalg.norm(rows.xyz[linked] - truth[:3, 3]) > 0.02
        mid = log.ego_pose_at((times[5] + times[6]) // 2)
        np.testing.assert_allclose(mid[:3, 3], (rows.xyz[5] + rows.xyz[6]) / 2)
        # up to POSE_EDGE_LIMIT_US beyond the table, the two end rows are extrapolated; farther, no pose at all
        step = rows.xyz[-1] - rows.xyz[-2]
        np.testing.assert_allclose(log.ego_pose_at(times[-1] + POSE_PERIOD_US)[:3, 3], rows.xyz[-1] + step, atol=1e-9)
        np.testing.assert_allclose(log.ego_pose_at(times[0])[:3, 3], rows.xyz[0], atol=1e-12)
        with pytest.raises(PoseGapError, match="before the first usable ego_pose row"):
            log.ego_pose_at(times[0] - POSE_EDGE_LIMIT_US - 1)
        with pytest.raises(PoseGapError, match="after the last"):
            log.ego_pose_at(times[-1] + 10**9)


def test_slerp_halves_the_rotation_angle():
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    q1 = np.array([np.cos(1.0), 0.0, 0.0, np.sin(1.0)])  # 2 rad about z
    np.testing.assert_allclose(slerp(q0, q1, 0.5), [np.cos(0.5), 0, 0, np.sin(0.5)], atol=1e-12)
    np.testing.assert_allclose(slerp(q0, -q1, 0.25), [np.cos(0.25), 0, 0, np.sin(0.25)], atol=1e-12)


def test_db_pins_the_format_facts(built, db_path):
    db = sqlite3.connect(db_path)
    tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    assert tables == {"camera", "category", "ego_pose", "image", "lidar", "lidar_box", "lidar_pc", "log",
                      "scenario_tag", "scene", "track", "traffic_light_status"}
    for table in ("log", "lidar_pc", "lidar_box", "ego_pose", "track", "scene"):
        assert db.execute(f"SELECT DISTINCT typeof(token), length(token) FROM {table}").fetchall() == [("blob", 8)]
    assert sorted(r[0] for r in db.execute("SELECT name FROM category")) == sorted(NUPLAN_CATEGORIES)
    translation, rotation = db.execute("SELECT translation, rotation FROM lidar WHERE channel='MergedPointCloud'").fetchone()
    assert b"nuplan" not in translation and pickle.loads(translation) == pytest.approx([1.5185, 0.0, 1.6309])
    assert type(pickle.loads(rotation)) is list
    assert db.execute("SELECT typeof(timestamp) FROM lidar_pc LIMIT 1").fetchone() == ("integer",)
    steps = [r[0] for r in db.execute("SELECT timestamp FROM lidar_pc ORDER BY timestamp")]
    assert set(np.diff(steps)) == {50_000}
    # lidar_box chains follow each track in time
    for (track,) in db.execute("SELECT token FROM track"):
        chain = db.execute("SELECT lb.token, lb.prev_token, lb.next_token FROM lidar_box lb JOIN lidar_pc lp "
                           "ON lp.token = lb.lidar_pc_token WHERE lb.track_token = ? ORDER BY lp.timestamp",
                           (track,)).fetchall()
        assert chain[0][1] is None and chain[-1][2] is None
        assert all(a[2] == b[0] and b[1] == a[0] for a, b in zip(chain, chain[1:]))
    db.close()


def test_yaw_of_ego_boxes_is_relative_to_ego_heading(built, db_path):
    with NuplanLog(db_path) as log:
        frame = log.frames[4]
        ego = log.boxes(frame, "ego")
        k = ego.categories.index("traffic_cone")
        heading = np.arctan2(log.frame_pose(frame)[1, 0], log.frame_pose(frame)[0, 0])
        R = yaw_matrix(ego.yaws[k] + heading)
        np.testing.assert_allclose(R, yaw_matrix(0.0), atol=1e-9)
        np.testing.assert_allclose(ego.centers[k], transform_points(invert_transform(log.frame_pose(frame)),
                                                                    log.boxes(frame).centers[k])[0])
