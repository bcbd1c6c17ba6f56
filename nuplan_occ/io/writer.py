"""Writes a LogContent as a nuPlan log: the SQLite DB of nuPlan's log schema plus PCD blobs.

Layout under data_root (as in the released nuPlan data):
  <data_root>/nuplan-v1.1/splits/<split>/<meta.logfile>.db
  <data_root>/nuplan-v1.1/sensor_blobs/<frame.filename>        (binary PCD, points in the "lidar" frame)
Tokens are hex strings in LogContent and 8-byte (or whatever length the hex gives) BLOBs in the DB;
timestamps are integer µs; boxes and ego poses are in the "global" (UTM) frame.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import sqlite3
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np

from nuplan_occ.geometry import matrix_to_quaternion
from nuplan_occ.io.pcd import encode_pcd
from nuplan_occ.io.types import LIDAR_CHANNEL, NUPLAN_CATEGORIES, LidarFrame, LogContent, PointCloud

DDL = """
CREATE TABLE log (
    token BLOB NOT NULL, vehicle_name VARCHAR(64), date VARCHAR(64), timestamp INTEGER,
    logfile VARCHAR(64), location VARCHAR(64), map_version VARCHAR(64), PRIMARY KEY (token));
CREATE TABLE category (token BLOB NOT NULL, name VARCHAR(64), description TEXT, PRIMARY KEY (token));
CREATE TABLE lidar (
    token BLOB NOT NULL, log_token BLOB NOT NULL REFERENCES log(token), channel VARCHAR(64), model VARCHAR(64),
    translation BLOB, rotation BLOB, PRIMARY KEY (token));
CREATE TABLE camera (
    token BLOB NOT NULL, log_token BLOB NOT NULL REFERENCES log(token), channel VARCHAR(64), model VARCHAR(64),
    translation BLOB, rotation BLOB, intrinsic BLOB, distortion BLOB, width INTEGER, height INTEGER,
    PRIMARY KEY (token));
CREATE TABLE ego_pose (
    token BLOB NOT NULL, timestamp INTEGER, x FLOAT, y FLOAT, z FLOAT, qw FLOAT, qx FLOAT, qy FLOAT, qz FLOAT,
    vx FLOAT, vy FLOAT, vz FLOAT, acceleration_x FLOAT, acceleration_y FLOAT, acceleration_z FLOAT,
    angular_rate_x FLOAT, angular_rate_y FLOAT, angular_rate_z FLOAT, epsg INTEGER,
    log_token BLOB NOT NULL REFERENCES log(token), PRIMARY KEY (token));
CREATE TABLE scene (
    token BLOB NOT NULL, log_token BLOB NOT NULL REFERENCES log(token), name TEXT,
    goal_ego_pose_token BLOB REFERENCES ego_pose(token), roadblock_ids TEXT, PRIMARY KEY (token));
CREATE TABLE lidar_pc (
    token BLOB NOT NULL, next_token BLOB REFERENCES lidar_pc(token), prev_token BLOB REFERENCES lidar_pc(token),
    ego_pose_token BLOB NOT NULL REFERENCES ego_pose(token), lidar_token BLOB NOT NULL REFERENCES lidar(token),
    scene_token BLOB NOT NULL REFERENCES scene(token), filename VARCHAR(128), timestamp INTEGER,
    PRIMARY KEY (token));
CREATE TABLE image (
    token BLOB NOT NULL, next_token BLOB REFERENCES image(token), prev_token BLOB REFERENCES image(token),
    ego_pose_token BLOB NOT NULL REFERENCES ego_pose(token), camera_token BLOB NOT NULL REFERENCES camera(token),
    filename_jpg VARCHAR(128), timestamp INTEGER, PRIMARY KEY (token));
CREATE TABLE track (
    token BLOB NOT NULL, category_token BLOB NOT NULL REFERENCES category(token),
    width FLOAT, length FLOAT, height FLOAT, PRIMARY KEY (token));
CREATE TABLE lidar_box (
    token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL REFERENCES lidar_pc(token),
    track_token BLOB REFERENCES track(token), next_token BLOB REFERENCES lidar_box(token),
    prev_token BLOB REFERENCES lidar_box(token), x FLOAT, y FLOAT, z FLOAT, width FLOAT, length FLOAT,
    height FLOAT, vx FLOAT, vy FLOAT, vz FLOAT, yaw FLOAT, confidence FLOAT, PRIMARY KEY (token));
CREATE TABLE scenario_tag (
    token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL REFERENCES lidar_pc(token), type TEXT,
    agent_track_token BLOB REFERENCES track(token), PRIMARY KEY (token));
CREATE TABLE traffic_light_status (
    token BLOB NOT NULL, lidar_pc_token BLOB NOT NULL REFERENCES lidar_pc(token), lane_connector_id INTEGER,
    status VARCHAR(8), PRIMARY KEY (token));
"""
"""The 12 tables of nuPlan's log schema, and no index the devkit's schema does not declare (the reader
must be fast without one)."""

PointSource = Callable[[LidarFrame], PointCloud | None]


def new_token(rng: np.random.Generator) -> str:
    """A fresh 8-byte token as 16 lowercase hex characters."""
    return rng.bytes(8).hex()


def category_token(name: str) -> str:
    """Deterministic 8-byte hex token of a category row."""
    return hashlib.blake2b(name.encode(), digest_size=8).hexdigest()


def log_db_path(data_root: str | Path, split: str, logfile: str) -> Path:
    """Where write_log puts the DB of a log."""
    return Path(data_root) / "nuplan-v1.1" / "splits" / split / f"{logfile}.db"


def sensor_blobs_root(data_root: str | Path) -> Path:
    """The sensor_blobs folder under a data root (filenames in the DB are relative to it)."""
    return Path(data_root) / "nuplan-v1.1" / "sensor_blobs"


def _blob(token: str | None) -> bytes | None:
    return None if token is None else bytes.fromhex(token)


def _pickled(values: Iterable) -> bytes:
    """Calibration column: a plain (nested) list of floats, pickle protocol 4."""
    return pickle.dumps(np.asarray(values, dtype=np.float64).tolist(), protocol=4)


def _chain(tokens_in_order: Sequence[str]) -> dict[str, tuple[str | None, str | None]]:
    """token -> (prev, next) along an ordered sequence; None at the ends."""
    out = {}
    for i, token in enumerate(tokens_in_order):
        prev = tokens_in_order[i - 1] if i > 0 else None
        nxt = tokens_in_order[i + 1] if i + 1 < len(tokens_in_order) else None
        out[token] = (prev, nxt)
    return out


def _check(content: LogContent) -> None:
    """Raise ValueError on content the DB cannot represent consistently."""
    track_tokens = {t.token for t in content.tracks}
    frame_tokens = {f.token for f in content.frames}
    bad_categories = {t.category for t in content.tracks} - set(NUPLAN_CATEGORIES)
    if bad_categories:
        raise ValueError(f"unknown categories {sorted(bad_categories)}; expected one of {NUPLAN_CATEGORIES}")
    for frame_token, boxes in content.boxes.items():
        if frame_token not in frame_tokens:
            raise ValueError(f"boxes given for unknown lidar_pc token {frame_token}")
        if boxes.frame != "global":
            raise ValueError(f"boxes of frame {frame_token} are in the {boxes.frame!r} frame, expected 'global'")
        unknown = set(boxes.track_tokens) - track_tokens
        if unknown:
            raise ValueError(f"boxes of frame {frame_token} refer to unknown tracks {sorted(unknown)}")


def _insert_calibration(db: sqlite3.Connection, content: LogContent) -> None:
    log_token = _blob(content.meta.token)
    lidar = content.lidar
    db.execute(
        "INSERT INTO lidar (token, log_token, channel, model, translation, rotation) VALUES (?,?,?,?,?,?)",
        (_blob(lidar.token), log_token, LIDAR_CHANNEL, lidar.model,
         _pickled(lidar.T_ego_from_lidar[:3, 3]), _pickled(matrix_to_quaternion(lidar.T_ego_from_lidar[:3, :3]))),
    )
    db.executemany(
        "INSERT INTO camera (token, log_token, channel, model, translation, rotation, intrinsic, distortion, "
        "width, height) VALUES (?,?,?,?,?,?,?,?,?,?)",
        [(_blob(c.token), log_token, c.channel, c.model, _pickled(c.T_ego_from_camera[:3, 3]),
          _pickled(matrix_to_quaternion(c.T_ego_from_camera[:3, :3])), _pickled(c.K), _pickled(c.distortion),
          int(c.width), int(c.height)) for c in content.cameras],
    )


def _insert_log_rows(db: sqlite3.Connection, content: LogContent) -> None:
    meta = content.meta
    log_token = _blob(meta.token)
    db.execute(
        "INSERT INTO log (token, vehicle_name, date, timestamp, logfile, location, map_version) "
        "VALUES (?,?,?,?,?,?,?)",
        (log_token, meta.vehicle_name, meta.date, int(meta.timestamp_us), meta.logfile, meta.location,
         meta.map_name),
    )
    db.executemany(
        "INSERT INTO category (token, name, description) VALUES (?,?,?)",
        [(_blob(category_token(name)), name, f"{name}.") for name in NUPLAN_CATEGORIES],
    )
    _insert_calibration(db, content)
    db.executemany(
        "INSERT INTO ego_pose (token, timestamp, x, y, z, qw, qx, qy, qz, vx, vy, vz, acceleration_x, "
        "acceleration_y, acceleration_z, angular_rate_x, angular_rate_y, angular_rate_z, epsg, log_token) "
        "VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
        [(_blob(p.token), int(p.timestamp_us), *map(float, p.T_global_from_ego[:3, 3]),
          *map(float, matrix_to_quaternion(p.T_global_from_ego[:3, :3])), *map(float, p.velocity),
          *map(float, p.acceleration), *map(float, p.angular_rate), int(p.epsg), log_token)
         for p in content.ego_poses],
    )
    db.executemany(
        "INSERT INTO scene (token, log_token, name, goal_ego_pose_token, roadblock_ids) VALUES (?,?,?,?,?)",
        [(_blob(s.token), log_token, s.name, _blob(s.goal_ego_pose_token), " ".join(s.roadblock_ids))
         for s in content.scenes],
    )


def _insert_sensor_rows(db: sqlite3.Connection, content: LogContent) -> None:
    frames = sorted(content.frames, key=lambda f: (f.timestamp_us, f.token))
    chain = _chain([f.token for f in frames])
    db.executemany(
        "INSERT INTO lidar_pc (token, next_token, prev_token, ego_pose_token, lidar_token, scene_token, filename, "
        "timestamp) VALUES (?,?,?,?,?,?,?,?)",
        [(_blob(f.token), _blob(chain[f.token][1]), _blob(chain[f.token][0]), _blob(f.ego_pose_token),
          _blob(f.lidar_token), _blob(f.scene_token), f.filename, int(f.timestamp_us)) for f in frames],
    )
    per_camera = defaultdict(list)
    for image in sorted(content.images, key=lambda i: (i.timestamp_us, i.token)):
        per_camera[image.camera_token].append(image)
    rows = []
    for images in per_camera.values():
        image_chain = _chain([i.token for i in images])
        rows += [(_blob(i.token), _blob(image_chain[i.token][1]), _blob(image_chain[i.token][0]),
                  _blob(i.ego_pose_token), _blob(i.camera_token), i.filename_jpg, int(i.timestamp_us))
                 for i in images]
    db.executemany(
        "INSERT INTO image (token, next_token, prev_token, ego_pose_token, camera_token, filename_jpg, timestamp) "
        "VALUES (?,?,?,?,?,?,?)",
        rows,
    )


def _insert_boxes(db: sqlite3.Connection, content: LogContent) -> None:
    db.executemany(
        "INSERT INTO track (token, category_token, width, length, height) VALUES (?,?,?,?,?)",
        [(_blob(t.token), _blob(category_token(t.category)), float(t.width), float(t.length), float(t.height))
         for t in content.tracks],
    )
    frame_time = {f.token: (f.timestamp_us, f.token) for f in content.frames}
    per_track: dict[str, list[tuple[tuple[int, str], str, int]]] = defaultdict(list)
    for frame_token, boxes in content.boxes.items():
        for k, track in enumerate(boxes.track_tokens):
            per_track[track].append((frame_time[frame_token], frame_token, k))
    rows = []
    for entries in per_track.values():
        entries.sort()
        chain = _chain([content.boxes[frame_token].tokens[k] for _, frame_token, k in entries])
        for _, frame_token, k in entries:
            b = content.boxes[frame_token]
            token = b.tokens[k]
            length, width, height = map(float, b.sizes[k])
            rows.append((_blob(token), _blob(frame_token), _blob(b.track_tokens[k]), _blob(chain[token][1]),
                         _blob(chain[token][0]), *map(float, b.centers[k]), width, length, height,
                         *map(float, b.velocities[k]), float(b.yaws[k]), 1.0))
    db.executemany(
        "INSERT INTO lidar_box (token, lidar_pc_token, track_token, next_token, prev_token, x, y, z, width, "
        "length, height, vx, vy, vz, yaw, confidence) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
        rows,
    )


def write_db(content: LogContent, db_path: str | Path) -> Path:
    """Write the log DB atomically (temporary file in the same folder, then rename). Returns db_path."""
    _check(content)
    db_path = Path(db_path)
    db_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = db_path.with_name(f".{db_path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        db = sqlite3.connect(tmp)
        try:
            with db:
                db.executescript(DDL)
                _insert_log_rows(db, content)
                _insert_sensor_rows(db, content)
                _insert_boxes(db, content)
        finally:
            db.close()
        os.replace(tmp, db_path)
    finally:
        tmp.unlink(missing_ok=True)
    return db_path


def write_blob(path: Path, data: bytes) -> None:
    """Write a sensor blob atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_log(
    content: LogContent,
    data_root: str | Path,
    split: str = "mini",
    point_source: PointSource | None = None,
) -> Path:
    """Write one log under data_root; returns the DB path.

    point_source(frame) gives that frame's cloud in the "lidar" frame (T_ego_from_lidar = content.lidar's
    extrinsic), or None to leave its blob missing; without point_source no blobs are written.
    Raises ValueError on inconsistent content (unknown category or track, boxes not in the global frame).
    """
    db_path = write_db(content, log_db_path(data_root, split, content.meta.logfile))
    if point_source is not None:
        blobs = sensor_blobs_root(data_root)
        for frame in content.frames:
            cloud = point_source(frame)
            if cloud is not None:
                write_blob(blobs / frame.filename, encode_pcd(cloud))
    return db_path
