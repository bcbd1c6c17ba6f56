"""The synthetic camera rig: nuPlan's 8 cameras (`camera` rows) and their images' `image` rows.

Cameras: pinhole with Brown-Conrady ("Caltech") lens distortion [k1, k2, p1, p2, k3] as OpenCV applies it,
OpenCV camera axes (x right, y down, z forward), pixel (column c, row r) centred at (u, v) = (c, r) (OpenCV's
convention; u across, v down). All 8 sit on the roof 0.6 m out from (1.6, 0, 1.75) m (ego frame), level,
facing the yaws of `CAMERA_YAW_DEG` (CAM_F0 forward, L to the left, R to the right, B0 backward); images are
IMAGE_WIDTH x IMAGE_HEIGHT px, every camera's field of view about 64 x 39 degrees (before distortion widens it).

Images are taken at the time of a lidar_pc row and reuse its ego_pose_token (the devkit joins image to
lidar_pc on that token and matches them within 50 ms of the lidar_pc timestamp); filename_jpg is
`<logfile>/<channel>/<token>.jpg`, relative to sensor_blobs/.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import make_transform
from nuplan_occ.io.types import CAMERA_CHANNELS, CameraCalibration, ImageRecord, LidarFrame
from nuplan_occ.io.writer import new_token

IMAGE_WIDTH, IMAGE_HEIGHT = 480, 270
"""Image size (px): a quarter of nuPlan's 1920 x 1080 in each direction."""
CAMERA_YAW_DEG = {"CAM_F0": 0, "CAM_L0": 55, "CAM_L1": 110, "CAM_L2": 150, "CAM_B0": 180, "CAM_R0": -55,
                  "CAM_R1": -110, "CAM_R2": -150}
"""Heading of each camera's optical axis about ego +z (deg, 0 = forward, positive to the left)."""
_FULL_SIZE_SCALE = IMAGE_WIDTH / 1920
"""Intrinsics are drawn for a 1920 x 1080 sensor and scaled by this power of two (so the camera rays of
`nuplan_occ.rays.visibility` are the same at either size, bit for bit)."""


def camera_rig(rng: np.random.Generator) -> list[CameraCalibration]:
    """The 8 cameras of a log, with small per-log differences in focal length, principal point and
    distortion drawn from rng (T_ego_from_camera: camera -> ego, OpenCV axes; see module doc)."""
    out = []
    for channel in CAMERA_CHANNELS:
        yaw = np.radians(CAMERA_YAW_DEG[channel])
        forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        R = np.stack([right, np.array([0.0, 0.0, -1.0]), forward], axis=1)  # columns: camera axes in ego
        position = np.array([1.6, 0.0, 1.75]) + 0.6 * forward * [1.0, 1.0, 0.0]
        f = 1545.0 * rng.uniform(0.98, 1.02)
        K = np.array([[f, 0.0, 960.0 + rng.normal(0, 4)], [0.0, f, 560.0 + rng.normal(0, 4)], [0.0, 0.0, 1.0]])
        K[:2] *= _FULL_SIZE_SCALE
        dist = np.array([-0.35, 0.12, 0.0, 0.0, -0.02]) + rng.normal(0, [0.01, 0.005, 1e-4, 1e-4, 0.002])
        out.append(CameraCalibration(new_token(rng), channel, "synthetic-pinhole", K, dist, make_transform(R, position),
                                     IMAGE_WIDTH, IMAGE_HEIGHT))
    return out


def distort(xy: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """Distorted normalized image coordinates (N, 2) of undistorted ones xy (N, 2) = (x / z, y / z) in the
    camera frame, Brown-Conrady [k1, k2, p1, p2, k3] (pixel = K @ [x_d, y_d, 1])."""
    k1, k2, p1, p2, k3 = np.asarray(distortion, dtype=np.float64)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.stack([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                     y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], axis=1)


def undistort(xy_distorted: np.ndarray, distortion: np.ndarray, max_iterations: int = 20) -> np.ndarray:
    """Undistorted normalized coordinates (N, 2) whose `distort` is xy_distorted (N, 2): Newton's method
    on the distortion map from the distorted point, with a numerical Jacobian. ValueError when some point
    has not converged to 1e-10 after max_iterations (outside the part where the map is one-to-one)."""
    target = np.asarray(xy_distorted, dtype=np.float64)
    xy, h = target.copy(), 1e-7
    for _ in range(max_iterations):
        at = distort(xy, distortion)
        residual = at - target
        if np.all(np.abs(residual) < 1e-10):
            return xy
        jx = (distort(xy + [h, 0.0], distortion) - at) / h
        jy = (distort(xy + [0.0, h], distortion) - at) / h
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        xy -= np.stack([jy[:, 1] * residual[:, 0] - jy[:, 0] * residual[:, 1],
                        jx[:, 0] * residual[:, 1] - jx[:, 1] * residual[:, 0]], axis=1) / det[:, None]
    raise ValueError("undistort: lens distortion is not invertible over these points")


def pixel_rays(camera: CameraCalibration) -> np.ndarray:
    """(height, width, 3) unit directions in the camera frame (OpenCV axes) of the rays through every
    pixel centre of the camera's image, lens distortion included (module doc)."""
    K = np.asarray(camera.K, dtype=np.float64)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    y = (v.ravel() - K[1, 2]) / K[1, 1]
    x = (u.ravel() - K[0, 2] - K[0, 1] * y) / K[0, 0]
    xy = undistort(np.stack([x, y], axis=1), camera.distortion)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d.reshape(camera.height, camera.width, 3)


def project(camera: CameraCalibration, points_ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) [u, v] (lens distortion applied) and depth z (N,) m along the optical axis
    of points (N, 3) in the ego frame; points with z <= 0 are behind the camera (their uv is meaningless), and
    so is the uv of points far outside the pinhole frustum of K and the image size, where the distortion
    polynomial is no longer one-to-one and folds them back into the image."""
    T = np.linalg.inv(np.asarray(camera.T_ego_from_camera, dtype=np.float64))
    p = np.asarray(points_ego, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    z = p[:, 2]
    xy = distort(p[:, :2] / np.where(z > 0, z, 1.0)[:, None], camera.distortion)
    K = np.asarray(camera.K, dtype=np.float64)
    uv = np.stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]], axis=1)
    return uv, z


def image_records(frames: list[LidarFrame], cameras: list[CameraCalibration], logfile: str, every: int,
                  rng: np.random.Generator) -> list[ImageRecord]:
    """`image` rows: one per camera at every `every`-th lidar_pc (index 0, every, 2 every, ...), with that
    frame's timestamp and ego_pose_token; tokens from rng (prev/next are chained by the writer)."""
    out = []
    for frame in frames[::every]:
        for camera in cameras:
            token = new_token(rng)
            out.append(ImageRecord(token, frame.timestamp_us, f"{logfile}/{camera.channel}/{token}.jpg", camera.token,
                                   frame.ego_pose_token))
    return out
