"""Sensor metadata of output frames: each camera's image and calibration, and the LiDAR's calibration.

For an output frame (a lidar_pc token at time t, µs) and each row of its log's `camera` table, one row
(`storage.sensors.SENSOR_SCHEMA`, stored per scene in `<root>/sensors/<log>/<scene_token>.parquet`):
    channel, camera_token, width, height: the camera row (px);
    intrinsic: K (3 x 3, px, row-major); distortion: [k1, k2, p1, p2, k3] (Brown-Conrady as OpenCV applies it
        to normalized coordinates; pixel = K @ [x_d, y_d, 1]); camera axes are OpenCV's (x right, y down, z
        forward);
    camera_to_ego: T_ego_from_camera (4 x 4 row-major, m), the camera row's extrinsic;
    lidar_to_ego: T_ego_from_lidar (4 x 4 row-major, m), the log's MergedPointCloud lidar row (the frame the
        sweeps are stored in); lidar_filename: the sweep's lidar_pc.filename (relative to sensor_blobs/);
    image_token, image_timestamp_us, image_filename (nuPlan's filename_jpg, relative to sensor_blobs/),
    image_path (the same file relative to the data root the metadata was read from), image_ego_to_frame_ego
        (T_ego(t)_from_ego(image time): the ego's motion between the sweep and the image, from the log's
        ego_pose table at both times; identity for an image taken at t; null when the log has no pose at one of
        them): the camera's `image` row nearest in time to t, when |image time - t| <= IMAGE_TOLERANCE_US; all
        null otherwise (or when the file name would leave sensor_blobs/, which is never opened).
The motion is relative, taken from the log's poses at both times, so it composes with any pose of the frame
(the dataset's ego_to_global may be refined by registration): camera-to-LiDAR at the frame's time is
inv(lidar_to_ego) @ image_ego_to_frame_ego @ camera_to_ego (`camera_to_lidar`).
`add_sensors(root, data_root)` writes the sidecars of an existing dataset from the logs it was built from.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nuplan_occ.geometry import invert_transform
from nuplan_occ.io.data_root import resolve_logs, sensor_root_for
from nuplan_occ.io.errors import MissingLogError, NuplanFormatError, PoseGapError
from nuplan_occ.io.reader import NuplanLog, leaves_folder
from nuplan_occ.storage.sensors import SENSOR_SCHEMA, write_sidecar

IMAGE_TOLERANCE_US = 50_000
"""An image matches a frame when taken within 50 ms of it: half the 10 Hz camera period, so each camera's
nearest image always matches in an unbroken log (the nuPlan devkit pairs images with sweeps the same way)."""


def _flat(matrix: np.ndarray) -> list[float]:
    return np.asarray(matrix, dtype=np.float64).ravel().tolist()


def frame_sensor_rows(log: NuplanLog, frames: Sequence[tuple[str, int]], scene_token: str,
                      image_prefix: str) -> pa.Table:
    """Sensor rows (module doc) of `frames` [(lidar_pc token, timestamp µs)] of one scene of `log`, frame
    after frame, each frame's cameras in the camera table's order. image_prefix: sensor_blobs/ relative to
    the data root (joined to filename_jpg to give image_path)."""
    images = log.images
    lidar_to_ego = _flat(log.lidar.T_ego_from_lidar)
    filenames = {frame.token: frame.filename for frame in log.frames}
    per_camera = []
    for camera in log.cameras:
        chosen = np.flatnonzero((images.camera_tokens == camera.token) & (images.timestamps_us >= 0))
        per_camera.append((camera, chosen, images.timestamps_us[chosen]))
    rows = []
    for token, t in frames:
        for camera, chosen, times in per_camera:
            row = {"token": token, "log": log.meta.logfile, "scene_token": scene_token, "timestamp_us": int(t),
                   "channel": camera.channel, "camera_token": camera.token, "width": camera.width,
                   "height": camera.height, "intrinsic": _flat(camera.K), "distortion": _flat(camera.distortion),
                   "camera_to_ego": _flat(camera.T_ego_from_camera), "lidar_to_ego": lidar_to_ego,
                   "lidar_filename": filenames.get(token),
                   "image_token": None, "image_filename": None, "image_path": None, "image_timestamp_us": None,
                   "image_ego_to_frame_ego": None}
            if len(times):
                k = int(np.argmin(np.abs(times - t)))
                name = images.filenames[chosen[k]].decode()
                if abs(int(times[k]) - t) <= IMAGE_TOLERANCE_US and name and not leaves_folder(name):
                    row |= {"image_token": str(images.tokens[chosen[k]]), "image_filename": name,
                            "image_path": f"{image_prefix}/{name}" if image_prefix else name,
                            "image_timestamp_us": int(times[k])}
                    try:
                        motion = invert_transform(log.ego_pose_at(int(t))) @ log.ego_pose_at(int(times[k]))
                        row["image_ego_to_frame_ego"] = _flat(motion)
                    except PoseGapError:
                        pass
            rows.append(row)
    return pa.Table.from_pylist(rows, schema=SENSOR_SCHEMA)


def camera_to_lidar(camera: dict, lidar_to_ego: np.ndarray) -> np.ndarray:
    """T_lidar_from_camera (4, 4) at the frame's time of one camera of `OccDataset.sensors`: the camera at its
    image's time carried into the frame's LiDAR frame by the ego's motion between them (module doc); without a
    known motion, through the ego frame alone."""
    motion = camera.get("image_ego_to_frame_ego")
    ego_from_camera = camera["camera_to_ego"] if motion is None else motion @ camera["camera_to_ego"]
    return invert_transform(lidar_to_ego) @ ego_from_camera


def add_sensors(root: str, data_root: str | Path, logs: Sequence[str] | None = None) -> dict:
    """Write the sensor sidecars of the dataset at `root` from the nuPlan logs under `data_root` (DBs found
    anywhere below it, sensor_blobs/ located as the build locates it); logs: only these log names (None: every
    log of the dataset; e.g. the logs one shard of a build wrote). Returns {"scenes": written, "frames",
    "rows", "without_image": rows with no image matched, "problems": [one line per log not found or not
    readable; its scenes get no sidecar]}. Frames of unknown log (an imported release without its logs) are
    left out."""
    from nuplan_occ.dataset import open_dataset

    summary = {"scenes": 0, "frames": 0, "rows": 0, "without_image": 0, "problems": []}
    if logs is not None and not logs:
        return summary
    wanted = None if logs is None else set(logs)
    ds = open_dataset(root)
    columns = ds.columns(["log", "scene_token", "token", "timestamp_us"])
    if wanted is not None:  # only the named logs' rows become Python objects (a build names its own logs)
        columns = columns.filter(pc.is_in(columns["log"], value_set=pa.array(sorted(wanted), pa.string())))
    table = columns.to_pylist()
    scenes: dict[str, dict[str, list[tuple[str, int]]]] = {}
    for row in table:
        if (row["log"] is not None and row["scene_token"] is not None and row["timestamp_us"] is not None
                and (wanted is None or row["log"] in wanted)):
            scenes.setdefault(row["log"], {}).setdefault(row["scene_token"], []).append(
                (row["token"], int(row["timestamp_us"])))
    try:
        dbs = {path.stem: path for path in resolve_logs(data_root, split=None)} if scenes else {}
    except NuplanFormatError as exc:
        summary["problems"].append(str(exc))
        return summary
    for log_name, by_scene in sorted(scenes.items()):
        try:
            if log_name not in dbs:
                raise MissingLogError(Path(data_root), f"no DB for log {log_name}")
            sensor_root = sensor_root_for(dbs[log_name], data_root)
            prefix = os.path.relpath(sensor_root, data_root).replace(os.sep, "/")
            with NuplanLog(dbs[log_name], sensor_root) as log:
                for scene_token, frames in sorted(by_scene.items()):
                    rows = frame_sensor_rows(log, sorted(frames, key=lambda f: f[1]), scene_token,
                                             "" if prefix == "." else prefix)
                    write_sidecar(root, log_name, scene_token, rows)
                    summary["scenes"] += 1
                    summary["frames"] += len(frames)
                    summary["rows"] += rows.num_rows
                    summary["without_image"] += rows.column("image_path").null_count
        except NuplanFormatError as exc:
            summary["problems"].append(f"log {log_name}: {exc}")
    return summary
