"""Builds a small hand-made nuPlan log (LogContent + per-frame clouds) with known ground truth, for tests.

The ego drives a circle of radius RADIUS m around CENTER (UTM, Las Vegas zone 11) at SPEED m/s, upright,
heading tangent to the circle. ego_pose rows are at 100 Hz, offset from the 20 Hz lidar_pc rows, and each
lidar_pc links to the nearest-but-earlier ego_pose (so the linked pose is *not* at the frame time).
Cloud points are sampled inside the boxes and on the ground, and stored in the "lidar" frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nuplan_occ.geometry import invert_transform, make_transform, transform_points, yaw_matrix
from nuplan_occ.io.types import (
    Boxes, CameraCalibration, EgoPoseRecord, ImageRecord, LidarCalibration, LidarFrame, LogContent, LogMeta,
    PointCloud, SceneRecord, TrackRecord,
)
from nuplan_occ.io.writer import new_token, write_log

CENTER = np.array([664000.0, 3997000.0, 600.0])
RADIUS = 40.0
SPEED = 10.0
T0_US = 1_620_858_198_150_622
LIDAR_PERIOD_US = 50_000
POSE_PERIOD_US = 10_000
POSE_OFFSET_US = -3_000
LOGFILE = "2021.05.12.22.00.38_veh-35_01008_01518"
T_EGO_FROM_LIDAR = make_transform(yaw_matrix(0.01), np.array([1.5185, 0.0, 1.6309]))


def true_pose(t_us: int | float) -> np.ndarray:
    """Ground-truth T_global_from_ego at time t (µs)."""
    theta = SPEED / RADIUS * (t_us - T0_US) / 1e6
    position = CENTER + RADIUS * np.array([np.cos(theta), np.sin(theta), 0.0])
    return make_transform(yaw_matrix(theta + np.pi / 2), position)


@dataclass
class BuiltLog:
    content: LogContent
    clouds: dict[str, PointCloud]        # lidar_pc token -> cloud in the "lidar" frame
    inside: dict[str, np.ndarray]        # lidar_pc token -> (N,) index of the box each point lies in, -1 ground


def _boxes_at(t_us: int, tracks: list[TrackRecord], box_tokens: list[str]) -> Boxes:
    """The three objects at time t in the global frame: a vehicle ahead on the circle, a walker, a cone."""
    theta = SPEED / RADIUS * (t_us - T0_US) / 1e6
    ahead = theta + 0.3
    vehicle = CENTER + (RADIUS + 3.5) * np.array([np.cos(ahead), np.sin(ahead), 0.0]) + [0, 0, 0.9]
    walker = CENTER + np.array([RADIUS + 8.0, 2.0 + 1.2 * (t_us - T0_US) / 1e6, 0.9])
    cone = CENTER + np.array([RADIUS - 6.0, 5.0, 0.35])
    return Boxes(
        frame="global",
        centers=np.stack([vehicle, walker, cone]),
        sizes=np.array([[t.length, t.width, t.height] for t in tracks]),
        yaws=np.array([ahead + np.pi / 2 - 2 * np.pi, np.pi / 2, 0.0]),
        velocities=np.array([[-SPEED * np.sin(ahead), SPEED * np.cos(ahead), 0.0], [0.0, 1.2, 0.0], [0.0, 0.0, 0.0]]),
        categories=[t.category for t in tracks], track_tokens=[t.token for t in tracks], tokens=box_tokens,
    )


def _cloud(boxes: Boxes, T_global_from_ego: np.ndarray, rng: np.random.Generator) -> tuple[PointCloud, np.ndarray]:
    """Points inside each box (80% of its half sizes) plus ground points, returned in the "lidar" frame."""
    parts, owner = [], []
    for k, T_global_from_box in enumerate(boxes.frame_from_box()):
        local = rng.uniform(-0.4, 0.4, size=(40, 3)) * boxes.sizes[k]
        parts.append(transform_points(T_global_from_box, local))
        owner.append(np.full(40, k))
    ground_ego = np.column_stack([rng.uniform(-20, 20, 60), rng.uniform(-20, 20, 60), np.zeros(60)])
    parts.append(transform_points(T_global_from_ego, ground_ego))
    owner.append(np.full(60, -1))
    xyz_global = np.concatenate(parts)
    T_lidar_from_global = invert_transform(T_global_from_ego @ T_EGO_FROM_LIDAR)
    n = len(xyz_global)
    cloud = PointCloud(xyz=transform_points(T_lidar_from_global, xyz_global),
                       intensity=rng.uniform(0, 255, n).astype(np.float32),
                       ring=rng.integers(0, 64, n).astype(np.int16),
                       lidar_info=(np.arange(n) % 5).astype(np.int8), frame="lidar")
    return cloud, np.concatenate(owner)


def build_log(seed: int = 0, n_frames: int = 10, n_scenes: int = 5) -> BuiltLog:
    """A LogContent of n_frames lidar_pc rows split evenly into n_scenes scenes, with its clouds."""
    rng = np.random.default_rng(seed)
    log_token = new_token(rng)
    meta = LogMeta(token=log_token, logfile=LOGFILE, vehicle_name="35", date="2021-05-12", timestamp_us=T0_US,
                   location="las_vegas", map_name="us-nv-las-vegas-strip")
    lidar = LidarCalibration(token=new_token(rng), channel="MergedPointCloud", model="merged",
                             T_ego_from_lidar=T_EGO_FROM_LIDAR)
    camera = CameraCalibration(token=new_token(rng), channel="CAM_F0", model="cam", K=np.array(
        [[1545.0, 0.0, 960.0], [0.0, 1545.0, 560.0], [0.0, 0.0, 1.0]]), distortion=np.array([-0.35, 0.1, 0.0, 0.0, 0.0]),
        T_ego_from_camera=make_transform(yaw_matrix(0.0), np.array([1.7, 0.0, 1.5])), width=1920, height=1080)
    lidar_times = [T0_US + i * LIDAR_PERIOD_US for i in range(n_frames)]
    pose_times = list(range(T0_US + POSE_OFFSET_US - 2 * POSE_PERIOD_US, lidar_times[-1] + 3 * POSE_PERIOD_US,
                            POSE_PERIOD_US))
    ego_poses = [EgoPoseRecord(token=new_token(rng), timestamp_us=t, T_global_from_ego=true_pose(t),
                               velocity=np.array([SPEED, 0.0, 0.0]), epsg=32611) for t in pose_times]
    scenes = [SceneRecord(token=new_token(rng), name=f"scene-{i:04d}", goal_ego_pose_token=ego_poses[-1].token,
                          roadblock_ids=[str(100 + i), str(200 + i)]) for i in range(n_scenes)]
    tracks = [TrackRecord(new_token(rng), "vehicle", width=2.0, length=4.6, height=1.8),
              TrackRecord(new_token(rng), "pedestrian", width=0.7, length=0.7, height=1.8),
              TrackRecord(new_token(rng), "traffic_cone", width=0.4, length=0.4, height=0.7)]
    frames, boxes, clouds, inside = [], {}, {}, {}
    for i, t in enumerate(lidar_times):
        token = new_token(rng)
        linked = [p for p in ego_poses if p.timestamp_us <= t][-1].token
        frames.append(LidarFrame(token=token, timestamp_us=t, filename=f"{LOGFILE}/MergedPointCloud/{token}.pcd",
                                 scene_token=scenes[i * n_scenes // n_frames].token, ego_pose_token=linked,
                                 lidar_token=lidar.token, index=i))
        boxes[token] = _boxes_at(t, tracks, [new_token(rng) for _ in tracks])
        clouds[token], inside[token] = _cloud(boxes[token], true_pose(t), rng)
    images = []
    for i, frame in enumerate(frames[::2]):
        token = new_token(rng)
        images.append(ImageRecord(token=token, timestamp_us=frame.timestamp_us + 1_000,
                                  filename_jpg=f"{LOGFILE}/CAM_F0/{token}.jpg", camera_token=camera.token,
                                  ego_pose_token=frame.ego_pose_token))
    content = LogContent(meta=meta, lidar=lidar, cameras=[camera], ego_poses=ego_poses, scenes=scenes[::-1],
                         frames=frames[::-1], tracks=tracks, boxes=boxes, images=images)
    return BuiltLog(content, clouds, inside)


def write_built(built: BuiltLog, data_root: Path, with_points: bool = True) -> Path:
    """Write the log under data_root (split "mini"); returns the DB path."""
    source = (lambda frame: built.clouds[frame.token]) if with_points else None
    return write_log(built.content, data_root, "mini", point_source=source)
