"""Occupancy -> per-camera depth and semantic maps (sparse Gaussian point maps), and the camera rigs.

Frames: Gaussians live in the ego frame (nuPlan rear axle, x forward, y left, z up, metres).
`CameraCalibration.T_ego_from_camera` maps camera-frame points (OpenCV: x right, y down, z forward)
into the ego frame. Depth maps hold the camera-frame z of the composited Gaussians (metres).

`default_rig()` is a plausible nuPlan-like rig (8 cameras, 1920 x 1080, f = 1545 px, strong barrel
distortion k1 = -0.356); for a real log use `rig_from_db`.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import GridSpec
from nuplan_occ.io.types import CAMERA_CHANNELS, CameraCalibration
from nuplan_occ.labels import LABELS
from occgen.exr import write_maps_exr
from occgen.gaussians import GaussianSet, gaussians_from_occupancy, rasterize
from occgen.unscented import COV_DILATION_PX2, ewa_project, project_points, unscented_project

NUM_CLASSES = max(LABELS.names) + 1
DEFAULT_K = np.array([[1545.0, 0.0, 960.0], [0.0, 1545.0, 560.0], [0.0, 0.0, 1.0]])
DEFAULT_DISTORTION = np.array([-0.356, 0.172, -0.00038, 0.00028, -0.0459])
PREVIEW_MAX_DEPTH_M = 60.0

# channel -> (x, y, z of the optical centre in the ego frame [m], yaw of the optical axis [deg], left positive)
_RIG_POSES = {
    "CAM_F0": ((1.70, 0.00, 1.60), 0.0),
    "CAM_L0": ((1.60, 0.45, 1.60), 55.0),
    "CAM_L1": ((1.00, 0.50, 1.60), 100.0),
    "CAM_L2": ((0.50, 0.45, 1.60), 145.0),
    "CAM_B0": ((0.30, 0.00, 1.60), 180.0),
    "CAM_R0": ((1.60, -0.45, 1.60), -55.0),
    "CAM_R1": ((1.00, -0.50, 1.60), -100.0),
    "CAM_R2": ((0.50, -0.45, 1.60), -145.0),
}


def camera_pose(position_ego: np.ndarray, yaw_deg: float, pitch_down_deg: float = 0.0) -> np.ndarray:
    """T_ego_from_camera (4, 4) of a camera at `position_ego` (m) looking along yaw, pitched down."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_down_deg)
    forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = position_ego
    return T


def default_rig() -> list[CameraCalibration]:
    """8 nuPlan-like cameras CAM_F0..CAM_R2 (poses in `_RIG_POSES`, shared K and distortion)."""
    return [
        CameraCalibration(
            token=f"{i:08x}", channel=ch, model="synthetic", K=DEFAULT_K.copy(),
            distortion=DEFAULT_DISTORTION.copy(),
            T_ego_from_camera=camera_pose(np.array(_RIG_POSES[ch][0]), _RIG_POSES[ch][1]),
            width=1920, height=1080,
        )
        for i, ch in enumerate(CAMERA_CHANNELS)
    ]


def rig_from_db(db_path: str | Path) -> list[CameraCalibration]:
    """The camera rows of a nuPlan log DB (raises the reader's errors on a bad DB or no cameras)."""
    from nuplan_occ.io.reader import NuplanLog

    with NuplanLog(db_path) as log:
        cameras = list(log.cameras)
    if not cameras:
        raise ValueError(f"{db_path}: the log has no camera rows")
    return cameras


def downscaled(camera: CameraCalibration, factor: int) -> CameraCalibration:
    """The same camera rendered at 1/factor resolution (pixel centres at integers, OpenCV)."""
    if factor == 1:
        return camera
    K = camera.K.astype(np.float64).copy()
    K[0, 0] /= factor
    K[0, 1] /= factor
    K[1, 1] /= factor
    K[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return replace(camera, K=K, width=camera.width // factor, height=camera.height // factor)


def render_camera(gaussians: GaussianSet, camera: CameraCalibration, method: str = "ut") -> dict[str, np.ndarray]:
    """Render one camera's maps (see `gaussians.rasterize`); method "ut" (unscented) or "ewa" (linearized)."""
    if method not in ("ut", "ewa"):
        raise ValueError(f"unknown projection method {method!r} (use 'ut' or 'ewa')")
    T = np.asarray(camera.T_ego_from_camera, dtype=np.float64)
    mu = torch.from_numpy((np.asarray(gaussians.means) - T[:3, 3]) @ T[:3, :3])  # camera frame
    # cull by the centres first (margin: a Gaussian of 3 sigma must still reach the image)
    uv, ok = project_points(mu, camera.K, camera.distortion)
    margin = 16.0
    ok &= (uv[:, 0] > -margin) & (uv[:, 0] < camera.width + margin) & (uv[:, 1] > -margin) & (uv[:, 1] < camera.height + margin)
    keep = torch.nonzero(ok).squeeze(1)
    mu = mu[keep]
    var = torch.from_numpy(np.asarray(gaussians.scale, dtype=np.float64)[keep.numpy()] ** 2)
    cov = var[:, None, None] * torch.eye(3, dtype=torch.float64)  # isotropic: rotation-invariant
    if method == "ut":
        mean2d, cov2d, valid = unscented_project(mu, cov, camera.K, camera.distortion)
    else:
        mean2d, cov2d, valid = ewa_project(mu, cov, camera.K)
    cov2d = cov2d + COV_DILATION_PX2 * torch.eye(2, dtype=cov2d.dtype)
    sel = torch.nonzero(valid).squeeze(1)
    src = keep[sel].numpy()
    return rasterize(
        mean2d[sel], cov2d[sel], mu[sel, 2],
        torch.from_numpy(np.asarray(gaussians.labels)[src].astype(np.int64)),
        torch.from_numpy(np.asarray(gaussians.opacity, dtype=np.float64)[src]),
        camera.width, camera.height, NUM_CLASSES,
    )


def preview_image(maps: dict[str, np.ndarray]) -> np.ndarray:
    """(2H, W, 3) uint8: semantic colours above, depth (near bright, 0..60 m) below."""
    sem = LABELS.palette()[maps["semantic"]]
    d = np.clip(maps["depth"] / PREVIEW_MAX_DEPTH_M, 0.0, 1.0)
    gray = np.where(maps["alpha"] > 0, 255 * (1.0 - d), 0).astype(np.uint8)
    return np.concatenate([sem, np.repeat(gray[..., None], 3, axis=2)], axis=0)


def render_frame(
    semantics: np.ndarray, grid: GridSpec, cameras: list[CameraCalibration], method: str = "ut", scale: float = 0.01,
) -> dict[str, dict[str, np.ndarray]]:
    """Maps of every camera (channel -> maps) for one semantic grid indexed [x, y, z] on `grid`."""
    gaussians = gaussians_from_occupancy(semantics, grid, scale=scale)
    return {cam.channel: render_camera(gaussians, cam, method) for cam in cameras}


def render_maps(
    root: str, frames: list[int], out_dir: str | Path, cameras: list[CameraCalibration] | None = None,
    downscale: int = 4, method: str = "ut", scale: float = 0.01,
) -> list[Path]:
    """Render frames (dataset indices) of the dataset at `root` for each camera.

    Writes `<out_dir>/<token>/<channel>.exr` (depth, alpha, semantic; see occgen.exr) and
    `<channel>.png` (preview). cameras: None -> `default_rig()`; every camera is rendered at
    1/downscale resolution. Returns the written EXR paths.
    """
    ds = open_dataset(root)
    rig = [downscaled(c, downscale) for c in (cameras if cameras is not None else default_rig())]
    written = []
    for i in frames:
        frame = ds.get(int(i), keys=["semantics"])
        folder = Path(out_dir) / frame["token"]
        folder.mkdir(parents=True, exist_ok=True)
        for channel, maps in render_frame(frame["semantics"], ds.grid, rig, method, scale).items():
            path = folder / f"{channel}.exr"
            write_maps_exr(path, maps["depth"], maps["alpha"], maps["semantic"])
            Image.fromarray(preview_image(maps)).save(folder / f"{channel}.png")
            written.append(path)
    return written
