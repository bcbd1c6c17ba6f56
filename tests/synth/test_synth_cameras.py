"""Synthetic camera rows, images and the truth's mask_camera: rows consistent with the images on disk, the
true voxels landing on pixels of their class, and a wall hiding what is behind it."""

from __future__ import annotations

import io
import sqlite3
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nuplan_occ.dataset import open_dataset
from nuplan_occ.evaluation.datasets import evaluate
from nuplan_occ.geometry import make_transform
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.io.types import CAMERA_CHANNELS, CameraCalibration
from nuplan_occ.io.writer import sensor_blobs_root
from nuplan_occ.labels import EMPTY
from nuplan_occ.synth import synthesize
from nuplan_occ.synth.camera_render import pixel_labels
from nuplan_occ.synth.cameras import IMAGE_HEIGHT, IMAGE_WIDTH, pixel_rays, project
from nuplan_occ.synth.truth import camera_mask

SECONDS = 0.3  # 6 sweeps; images at sweeps 0, 2, 4; truth at 10 Hz: sweeps 0, 2, 4


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_cameras")
    result = synthesize(root, logs=1, seconds=SECONDS, seed=5, truth_rate_hz=10.0, camera_rate_hz=10.0,
                        camera_mask=True)
    assert result.images == 3 * 8 and result.truth_frames == 3
    return root, result


def _image_rows(db_path: Path) -> list[dict]:
    """The `image` rows in time order (tokens as hex, None for NULL), read with plain SQL."""
    with sqlite3.connect(db_path) as db:
        db.row_factory = sqlite3.Row
        rows = db.execute("SELECT * FROM image ORDER BY timestamp, token").fetchall()
    return [{k: (r[k].hex() if isinstance(r[k], bytes) else r[k]) for k in r.keys()} for r in rows]


def _image(root: Path, filename_jpg: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO((sensor_blobs_root(root) / filename_jpg).read_bytes())).convert("RGB"))


def test_camera_and_image_rows_match_the_files(out):
    root, result = out
    blobs = sensor_blobs_root(root).resolve()
    with NuplanLog(result.db_paths[0]) as log:
        cameras = {c.token: c for c in log.cameras}
        assert sorted(c.channel for c in cameras.values()) == sorted(CAMERA_CHANNELS)
        assert all((c.width, c.height) == (IMAGE_WIDTH, IMAGE_HEIGHT) and len(c.distortion) == 5 for c in cameras.values())
        frame_at = {f.timestamp_us: f for f in log.frames}
        images = _image_rows(result.db_paths[0])
        assert len(images) == 3 * 8
        per_camera: dict[str, list] = {}
        for image in images:
            camera = cameras[image["camera_token"]]
            nearest = min(log.frames, key=lambda f: abs(f.timestamp_us - image["timestamp"]))
            assert abs(nearest.timestamp_us - image["timestamp"]) <= 50_000
            assert image["ego_pose_token"] == frame_at[image["timestamp"]].ego_pose_token
            assert image["filename_jpg"] == f"{log.meta.logfile}/{camera.channel}/{image['token']}.jpg"
            path = (blobs / image["filename_jpg"]).resolve()
            assert path.is_relative_to(blobs) and path.is_file()
            assert _image(root, image["filename_jpg"]).shape == (IMAGE_HEIGHT, IMAGE_WIDTH, 3)
            per_camera.setdefault(camera.channel, []).append(image)
        assert {len(images) for images in per_camera.values()} == {3}
        for chain in per_camera.values():  # prev/next chain each camera's images in time order
            assert [i["prev_token"] for i in chain] == [None] + [i["token"] for i in chain[:-1]]
            assert [i["next_token"] for i in chain] == [i["token"] for i in chain[1:]] + [None]
    # the devkit's image query: images within 50 ms of a lidar_pc, joined on the camera
    with sqlite3.connect(result.db_paths[0]) as db:
        rows = db.execute("SELECT lp.token, cam.channel FROM image AS img JOIN lidar_pc AS lp ON img.timestamp "
                          "BETWEEN lp.timestamp - 50000 AND lp.timestamp + 50000 AND img.ego_pose_token = "
                          "lp.ego_pose_token JOIN camera AS cam ON img.camera_token = cam.token").fetchall()
    assert len(rows) == 3 * 8 and len({token for token, _ in rows}) == 3


def test_truth_scores_itself_inside_its_camera_mask(out):
    root, _ = out
    truth = str(root / "truth")
    result = evaluate(truth, truth, mask="mask_camera")
    assert result["frames_matched"] == 3 and result["frames_without_mask"] == 0
    assert result["pooled"]["iou"] == 1.0 and 0 < result["pooled"]["n_voxels"] < 3 * np.prod(DEFAULT_GRID.shape)


def test_projection_inverts_the_pixel_rays(out):
    _, result = out
    with NuplanLog(result.db_paths[0]) as log:
        camera = log.cameras[0]
    rays = pixel_rays(camera).reshape(-1, 3)
    T = camera.T_ego_from_camera
    uv, depth = project(camera, (rays * 7.0) @ T[:3, :3].T + T[:3, 3])
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    assert np.abs(uv - np.stack([u.ravel(), v.ravel()], axis=1)).max() < 1e-6
    assert np.all(depth > 0)


def test_true_voxels_land_on_pixels_of_their_class(out):
    """Every occupied voxel of the first truth frame that mask_camera marks, projected (centre, stored
    calibration, distortion applied) into each image taken at that frame, where it lies in the camera's
    pinhole frustum (the mask's; beyond it the strong barrel distortion folds points back into the image):
    at least 85% land on a pixel whose colour, at the voxel's depth, is its class (93% at writing; the
    rest mostly road lines thinner than a voxel, whose voxel centre shows road, and voxels seen in part)."""
    root, result = out
    truth = open_dataset(str(root / "truth"))
    frame = truth.get(0, keys=("semantics", "mask_camera"))
    semantics, visible = frame["semantics"], frame["mask_camera"]
    voxels = np.argwhere((semantics != EMPTY) & visible)
    centers = DEFAULT_GRID.index_to_center(voxels)
    matched = total = 0
    with NuplanLog(result.db_paths[0]) as log:
        cameras = {c.token: c for c in log.cameras}
        images = _image_rows(result.db_paths[0])
        first = images[0]["timestamp"]
        assert first == frame["timestamp_us"]
        for image in (i for i in images if i["timestamp"] == first):
            camera = cameras[image["camera_token"]]
            uv, depth = project(camera, centers)
            pinhole, _ = project(replace(camera, distortion=np.zeros(5)), centers)
            ahead = (depth > 0.5) & np.all((pinhole >= -0.5) & (pinhole < [camera.width - 0.5, camera.height - 0.5]), axis=1)
            px = np.full(uv.shape, -1, np.int64)
            px[ahead] = np.rint(uv[ahead])
            inside = ahead & (px[:, 0] >= 0) & (px[:, 0] < camera.width) & (px[:, 1] >= 0) & (px[:, 1] < camera.height)
            rgb = _image(root, image["filename_jpg"])[px[inside, 1], px[inside, 0]]
            labels = pixel_labels(rgb, depth[inside])
            truth_labels = semantics[tuple(voxels[inside].T)]
            matched += int(np.count_nonzero(labels == truth_labels))
            total += int(np.count_nonzero(inside))
    assert total > 5_000
    assert matched / total >= 0.85, f"{matched} of {total} voxels on pixels of their class"


def test_mask_camera_wall_hides_what_is_behind_it():
    """A camera at the ego origin looking along +x (90 x 53 degree view), a wall 10 m ahead (y in [-5, 5] m,
    z in [-2, 3] m), one voxel in front of it and two behind it."""
    g = DEFAULT_GRID
    K = np.array([[100.0, 0.0, 100.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
    R = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: camera x, y, z in ego
    camera = CameraCalibration("c0", "CAM_F0", "test", K, np.zeros(5), make_transform(R, [0.0, 0.0, 0.0]), 200, 100)

    def index(x, y, z):
        return tuple(int(i) for i in g.point_to_index(np.array([[x, y, z]]))[0][0])

    semantics = np.zeros(g.shape, np.uint8)
    wall = index(10.1, -5.0, -2.0), index(10.1, 5.0, 3.0)
    semantics[wall[0][0], wall[0][1]:wall[1][1] + 1, wall[0][2]:wall[1][2] + 1] = 1
    front, hidden, beside = index(5.1, -2.1, 0.1), index(20.1, 0.1, 0.1), index(20.1, 15.1, 0.1)
    for voxel in (front, hidden, beside):
        semantics[voxel] = 2
    mask = camera_mask(semantics, [camera], g)
    assert mask[front] and mask[beside] and not mask[hidden]
    assert mask[wall[0][0], index(0, 0.1, 0.1)[1], index(0, 0.1, 0.1)[2]]  # the wall's face
    assert mask[index(8.0, 0.1, 0.1)] and not mask[index(12.0, 0.1, 0.1)] and not mask[index(30.0, 3.0, 0.1)]
    assert not mask[index(-5.0, 0.1, 0.1)]  # behind the camera
    assert not mask[index(5.0, 0.1, 4.6)] and not mask[index(5.0, 8.0, 0.1)]  # above and beside the view
