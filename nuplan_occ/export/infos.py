"""Per-frame info records as occupancy training code reads them from its info pickles.

Both consumers' loaders take a list of per-frame dicts in the layout that mmdetection3d's nuScenes info
files made common (UniScene v2's Nuplan-Occ renderer reads `infos['infos'][i]` by token, plus
`infos['scene_tokens']`; BEVDet / FlashOcc-style occupancy code reads `infos['infos'][i]['occ_path']`, `cams`,
`ego2global_*`, `lidar2ego_*`). One record (`frame_info`):
    token (lidar_pc hex), timestamp (µs), scene_token, scene_name, log_name, frame_idx (sweep index in the log);
    lidar_path: the sweep's file relative to sensor_blobs/;
    lidar2ego_translation (3,) m, lidar2ego_rotation (4,) quaternion w, x, y, z, lidar2ego (4, 4): T_ego_from_lidar;
    ego2global_translation, ego2global_rotation, ego2global: T_global_from_ego at the frame's time;
    cams: {channel: camera record} for every camera with an image matched to the frame (nuplan_occ.sensors):
        data_path: image file relative to sensor_blobs/ (nuPlan's filename_jpg); type: the channel;
        sample_data_token: image token; timestamp: image time (µs); width, height (px);
        cam_intrinsic (3, 3) px; distortion (5,) k1, k2, p1, p2, k3 (OpenCV's model, camera axes OpenCV's);
        sensor2ego_translation, sensor2ego_rotation (quaternion w, x, y, z): T_ego_from_camera;
        ego2global_translation, ego2global_rotation: T_global_from_ego at the image's time (the frame's pose
            moved by the ego's motion to the image's time; left out when the frame's pose is unknown);
        sensor2lidar_rotation (3, 3), sensor2lidar_translation (3,): the camera at its image's time in the
            frame of the exported grid at the frame's time (`sensors.camera_to_lidar`): the LiDAR frame for
            grids in the LiDAR frame, the ego frame for grids left in the ego frame, so that a consumer placing
            cameras with it lands them on the grid either way.
Arrays are float64 numpy arrays (as in the consumers' own info files).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import invert_transform, make_transform, matrix_to_quaternion, transform_points
from nuplan_occ.sensors import camera_to_lidar
from nuplan_occ.synth.cameras import distort

FRUSTUM_MARGIN = 0.1
"""Points projected by the pinhole model beyond this share of the image size outside it are dropped."""


def _split(T: np.ndarray, prefix: str) -> dict:
    """{prefix_translation (3,), prefix_rotation (4,) w x y z} of a (4, 4) transform."""
    return {f"{prefix}_translation": np.array(T[:3, 3], dtype=np.float64),
            f"{prefix}_rotation": np.asarray(matrix_to_quaternion(T[:3, :3]), dtype=np.float64)}


def camera_record(channel: str, camera: dict, lidar_to_ego: np.ndarray, ego_to_global: np.ndarray,
                  grid_frame: str) -> dict:
    """One camera's record (module doc) of a frame whose pose is ego_to_global (T_global_from_ego, NaN where
    unknown) and LiDAR lidar_to_ego; grid_frame "lidar" | "ego": the frame sensor2lidar_* lead into."""
    motion = camera["image_ego_to_frame_ego"]
    image_pose = ego_to_global @ motion if motion is not None else ego_to_global
    grid_from_camera = camera_to_lidar(camera, lidar_to_ego if grid_frame == "lidar" else np.eye(4))
    record = {"data_path": camera["image_filename"], "type": channel, "sample_data_token": camera["image_token"],
              "timestamp": camera["image_timestamp_us"], "width": camera["width"], "height": camera["height"],
              "cam_intrinsic": camera["intrinsic"].copy(), "distortion": camera["distortion"].copy(),
              **_split(camera["camera_to_ego"], "sensor2ego"),
              "sensor2lidar_rotation": grid_from_camera[:3, :3].copy(),
              "sensor2lidar_translation": grid_from_camera[:3, 3].copy()}
    if np.all(np.isfinite(image_pose)):
        record |= _split(image_pose, "ego2global")
    return record


def frame_info(identity: dict, scene_name: str | None, sensors: dict | None, grid_frame: str) -> dict:
    """The info record of one frame (module doc). identity: `OccDataset.identity`; sensors: `OccDataset.sensors`
    or None (then lidar_path, lidar2ego_* and cams are left out, never invented); grid_frame: "lidar" | "ego"."""
    pose = identity["ego_to_global"]
    info = {"token": identity["token"], "timestamp": identity["timestamp_us"], "scene_token": identity["scene_token"],
            "scene_name": scene_name, "log_name": identity["log_name"], "frame_idx": identity["frame_index"]}
    if np.all(np.isfinite(pose)):
        info |= {**_split(pose, "ego2global"), "ego2global": pose.copy()}
    if sensors is None:
        return info
    lidar_to_ego = sensors["lidar_to_ego"]
    info |= {"lidar_path": sensors["lidar_filename"], **_split(lidar_to_ego, "lidar2ego"), "lidar2ego": lidar_to_ego.copy(),
             "cams": {channel: camera_record(channel, camera, lidar_to_ego, pose, grid_frame)
                      for channel, camera in sensors["cameras"].items() if camera["image_filename"] is not None}}
    return info


def project_to_image(points: np.ndarray, camera: dict) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) [u, v] and depths (N,) m (camera z) of points (N, 3) given in the exported grid's frame,
    with one camera record of an info file (sensor2lidar_*, cam_intrinsic, distortion: OpenCV's model), as a
    consumer projects them. Depth is set to -1 for points behind the camera and for points whose undistorted
    (pinhole) pixel lies more than FRUSTUM_MARGIN of the image size outside the image, where the distortion
    polynomial folds far points back into the picture; their pixel is meaningless."""
    grid_from_camera = make_transform(camera["sensor2lidar_rotation"], camera["sensor2lidar_translation"])
    p = transform_points(invert_transform(grid_from_camera), np.asarray(points, dtype=np.float64))
    depth = p[:, 2]
    K = camera["cam_intrinsic"]

    def pixels(xy: np.ndarray) -> np.ndarray:
        return np.stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]], axis=1)

    normalized = p[:, :2] / np.where(depth > 0, depth, 1.0)[:, None]
    size = np.array([camera["width"], camera["height"]], dtype=np.float64)
    pinhole = pixels(normalized)
    framed = (depth > 0) & np.all((pinhole > -FRUSTUM_MARGIN * size) & (pinhole < (1 + FRUSTUM_MARGIN) * size), axis=1)
    return pixels(distort(normalized, camera["distortion"])), np.where(framed, depth, -1.0)


def nearest_per_pixel(uv: np.ndarray, depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Indices of the points that are the nearest (smallest positive depth) of all points landing in their pixel
    (pixel (c, r) holds u, v in [c - 0.5, c + 0.5) x [r - 0.5, r + 0.5)): what a camera sees of them."""
    cell = np.floor(np.where((depth > 0)[:, None], uv, -1.0) + 0.5).astype(np.int64)
    col, row = cell[:, 0], cell[:, 1]
    inside = np.flatnonzero((depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height))
    pixel = row[inside] * width + col[inside]
    order = np.lexsort((depth[inside], pixel))
    first = np.ones(len(order), dtype=bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    return inside[order[first]]
