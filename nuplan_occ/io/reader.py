"""Reads one nuPlan log DB (SQLite, format reference section 2) and its LiDAR blobs, without the devkit.

Frames (see nuplan_occ.io.types): "global" = map UTM metres; "ego" = rear axle at a frame's time;
"lidar" = frame of the DB's MergedPointCloud lidar row (T_ego_from_lidar = its stored extrinsic).
Timestamps are integer µs. Tokens are exposed as lowercase hex of whatever BLOB length the DB stores.

The DB is opened read-only; columns are selected by name (extra columns are ignored), NULL chain ends
become None. A frame's pose is interpolated from the ego_pose table at the lidar_pc timestamp, because
ego_pose rows linked by token carry slightly different timestamps (format reference, 2.1).
"""

from __future__ import annotations

import re
import sqlite3
from functools import cached_property
from itertools import groupby
from pathlib import Path
from urllib.parse import quote

import numpy as np

from nuplan_occ.geometry import invert_transform, make_transform, quaternion_to_matrix
from nuplan_occ.io.data_root import guess_sensor_root
from nuplan_occ.io.errors import DatabaseError, MissingBlobError, PointCloudError, SchemaError, UnsafePickleError
from nuplan_occ.io.pcd import read_pcd
from nuplan_occ.io.pickles import load_calibration_blob
from nuplan_occ.io.types import (
    LIDAR_CHANNEL, NUPLAN_CATEGORIES, Boxes, CameraCalibration, EgoPoseRecord, ImageRecord, LidarCalibration,
    LidarFrame, LogMeta, PointCloud, SceneRecord, TrackRecord,
)

_REQUIRED: dict[str, tuple[str, ...]] = {
    "log": ("token", "logfile", "location", "map_version"),
    "lidar": ("token", "channel", "translation", "rotation"),
    "ego_pose": ("token", "timestamp", "x", "y", "z", "qw", "qx", "qy", "qz"),
    "scene": ("token", "name"),
    "lidar_pc": ("token", "next_token", "prev_token", "ego_pose_token", "lidar_token", "scene_token", "filename",
                 "timestamp"),
    "track": ("token", "category_token", "width", "length", "height"),
    "category": ("token", "name"),
    "lidar_box": ("token", "lidar_pc_token", "track_token", "x", "y", "z", "width", "length", "height", "yaw"),
}
"""Tables and columns without which a log cannot be read. camera and image are optional tables."""

_BOX_COLUMNS = ("lidar_pc_token", "token", "track_token", "x", "y", "z", "length", "width", "height", "yaw",
                "vx", "vy", "vz")


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions [w, x, y, z] (shortest arc); alpha in [0, 1]."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)


class NuplanLog:
    """One nuPlan log DB plus its sensor_blobs folder. Use as a context manager (closes the DB).

    sensor_root: the folder that lidar_pc.filename is relative to; by default the first `sensor_blobs`
    (or `nuplan-v1.1/sensor_blobs`) folder found next to an ancestor of the DB, else
    `<db>/../../../sensor_blobs` (the released layout), which may not exist (load_points then raises).

    A lidar_pc row with a NULL scene_token gets scene_token "" (the devkit's synthetic DDL allows NULL).
    Point helpers: points_to_ego(cloud, log) and points_to_global(cloud, log, frame) below.

    Raises DatabaseError (missing or non-SQLite file) and SchemaError (missing table/column/row, a
    non-BLOB token, a missing or duplicated MergedPointCloud lidar row, bad calibration) on opening.
    """

    def __init__(self, db_path: str | Path, sensor_root: str | Path | None = None):
        self.path = Path(db_path)
        if not self.path.is_file():
            raise DatabaseError(self.path, "log database file not found")
        guessed = guess_sensor_root(self.path)
        self.sensor_root = Path(sensor_root) if sensor_root is not None else guessed
        try:
            self._db = sqlite3.connect(f"file:{quote(str(self.path.resolve()))}?mode=ro", uri=True)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(self.path, f"cannot open SQLite database ({exc})") from None
        self._db.row_factory = sqlite3.Row
        try:
            self._load()
        except BaseException:
            self._db.close()
            raise
        self._frames_by_scene: dict[str, list[LidarFrame]] = {}
        for frame in self.frames:
            self._frames_by_scene.setdefault(frame.scene_token, []).append(frame)
        self._box_cache: dict[bytes, list[sqlite3.Row]] | None = None

    def _load(self) -> None:
        try:
            self._columns = self._read_columns()
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(self.path, f"not a readable SQLite database ({exc})") from None
        try:
            self.meta = self._read_meta()
            self.lidar = self._read_lidar()
            self.cameras = self._read_cameras()
            self.ego_poses, self._pose_q = self._read_ego_poses()
            self.scenes = self._read_scenes()
            self.frames = self._read_frames()
            self.images = self._read_images()
        except sqlite3.DatabaseError as exc:
            raise SchemaError(self.path, f"query failed ({exc})") from None
        self._pose_times = np.array([p.timestamp_us for p in self.ego_poses], dtype=np.int64)
        self._pose_xyz = np.array([p.T_global_from_ego[:3, 3] for p in self.ego_poses]).reshape(-1, 3)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Close the DB connection."""
        self._db.close()

    def __enter__(self) -> "NuplanLog":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ schema helpers
    def _read_columns(self) -> dict[str, set[str]]:
        tables = [r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        columns = {t: {r["name"] for r in self._db.execute(f'PRAGMA table_info("{t}")')} for t in tables}
        for table, needed in _REQUIRED.items():
            if table not in columns:
                raise SchemaError(self.path, f"table {table} is missing")
            missing = [c for c in needed if c not in columns[table]]
            if missing:
                raise SchemaError(self.path, f"table {table} lacks column(s) {', '.join(missing)}")
        return columns

    def _select(self, table: str, names: tuple[str, ...], tail: str = "", params: tuple = ()) -> list[sqlite3.Row]:
        """Rows of named columns; optional columns absent from the table come back as NULL."""
        cols = ", ".join(n if n in self._columns[table] else f"NULL AS {n}" for n in names)
        return self._db.execute(f"SELECT {cols} FROM {table} {tail}", params).fetchall()

    def _hex(self, value: object, where: str) -> str | None:
        """A BLOB token as lowercase hex (any length); NULL or empty -> None."""
        if value is None or value == b"":
            return None
        if not isinstance(value, bytes):
            raise SchemaError(self.path, f"{where} holds a {type(value).__name__} token, expected a BLOB")
        return value.hex()

    def _token(self, value: object, where: str) -> str:
        """A token that must not be NULL."""
        token = self._hex(value, where)
        if token is None:
            raise SchemaError(self.path, f"{where} is NULL")
        return token

    def _unpickle(self, row: sqlite3.Row, table: str, column: str) -> np.ndarray:
        """A pickled calibration column as a flat float64 array (UnsafePickleError names the DB and column)."""
        try:
            return load_calibration_blob(row[column], str(self.path)).reshape(-1)
        except UnsafePickleError as exc:
            raise UnsafePickleError(self.path, f"{table}.{column}: {exc.problem}") from None

    def _calibration(self, row: sqlite3.Row, table: str, column: str, size: int) -> np.ndarray:
        if row[column] is None:
            raise SchemaError(self.path, f"{table}.{column} is NULL")
        values = self._unpickle(row, table, column)
        if values.size != size or not np.all(np.isfinite(values)):
            raise SchemaError(self.path, f"{table}.{column} holds {values.size} values, expected {size} finite")
        if column == "rotation" and np.linalg.norm(values) < 1e-9:
            raise SchemaError(self.path, f"{table}.rotation is a zero quaternion")
        return values

    # ------------------------------------------------------------------ table readers
    def _read_meta(self) -> LogMeta:
        rows = self._select("log", ("token", "logfile", "vehicle_name", "date", "timestamp", "location",
                                    "map_version"), "LIMIT 1")
        if not rows:
            raise SchemaError(self.path, "table log has no row")
        r = rows[0]
        map_name = str(r["map_version"] or "")
        return LogMeta(
            token=self._token(r["token"], "log.token"), logfile=str(r["logfile"] or self.path.stem),
            vehicle_name=str(r["vehicle_name"] or ""), date=str(r["date"] or ""),
            timestamp_us=int(r["timestamp"] or 0), location=str(r["location"] or ""),
            map_name=map_name[:-5] if map_name.endswith(".gpkg") else map_name,
        )

    def _read_lidar(self) -> LidarCalibration:
        rows = self._select("lidar", ("token", "channel", "model", "translation", "rotation"),
                            "WHERE channel = ?", (LIDAR_CHANNEL,))
        if len(rows) != 1:
            raise SchemaError(self.path, f"expected one lidar row of channel {LIDAR_CHANNEL}, found {len(rows)}")
        r = rows[0]
        T = make_transform(quaternion_to_matrix(self._calibration(r, "lidar", "rotation", 4)),
                           self._calibration(r, "lidar", "translation", 3))
        return LidarCalibration(token=self._token(r["token"], "lidar.token"), channel=LIDAR_CHANNEL,
                                model=str(r["model"] or ""), T_ego_from_lidar=T)

    def _read_cameras(self) -> list[CameraCalibration]:
        if "camera" not in self._columns:
            return []
        rows = self._select("camera", ("token", "channel", "model", "translation", "rotation", "intrinsic",
                                       "distortion", "width", "height"), "ORDER BY channel")
        return [
            CameraCalibration(
                token=self._token(r["token"], "camera.token"), channel=str(r["channel"]), model=str(r["model"] or ""),
                K=self._calibration(r, "camera", "intrinsic", 9).reshape(3, 3),
                distortion=self._unpickle(r, "camera", "distortion") if r["distortion"] is not None else np.zeros(5),
                T_ego_from_camera=make_transform(quaternion_to_matrix(self._calibration(r, "camera", "rotation", 4)),
                                                 self._calibration(r, "camera", "translation", 3)),
                width=int(r["width"] or 0), height=int(r["height"] or 0),
            )
            for r in rows
        ]

    def _read_ego_poses(self) -> tuple[list[EgoPoseRecord], np.ndarray]:
        """The ego_pose rows in time order, and their unit quaternions [w, x, y, z] as an (N, 4) array."""
        rows = self._select("ego_pose", ("token", "timestamp", "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy",
                                         "vz", "acceleration_x", "acceleration_y", "acceleration_z",
                                         "angular_rate_x", "angular_rate_y", "angular_rate_z", "epsg"),
                            "ORDER BY timestamp, token")
        poses, quaternions = [], np.zeros((len(rows), 4))
        for i, r in enumerate(rows):
            token = self._token(r["token"], "ego_pose.token")
            try:
                q = np.array([r["qw"], r["qx"], r["qy"], r["qz"]], dtype=np.float64)
                t_us = int(r["timestamp"])
            except (TypeError, ValueError):
                raise SchemaError(self.path, f"ego_pose {token} has a NULL or non-numeric timestamp or quaternion") from None
            if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
                raise SchemaError(self.path, f"ego_pose {token} has an invalid quaternion {q.tolist()}")
            quaternions[i] = q / np.linalg.norm(q)

            def vec(*names: str) -> np.ndarray:
                return np.array([float(r[n] or 0.0) for n in names])

            poses.append(EgoPoseRecord(
                token=token, timestamp_us=t_us,
                T_global_from_ego=make_transform(quaternion_to_matrix(q), vec("x", "y", "z")),
                velocity=vec("vx", "vy", "vz"),
                acceleration=vec("acceleration_x", "acceleration_y", "acceleration_z"),
                angular_rate=vec("angular_rate_x", "angular_rate_y", "angular_rate_z"),
                epsg=int(r["epsg"] or 0),
            ))
        return poses, quaternions

    def _read_scenes(self) -> list[SceneRecord]:
        rows = self._select("scene", ("token", "name", "goal_ego_pose_token", "roadblock_ids"), "ORDER BY name")
        return [
            SceneRecord(token=self._token(r["token"], "scene.token"), name=str(r["name"]),
                        goal_ego_pose_token=self._hex(r["goal_ego_pose_token"], "scene.goal_ego_pose_token"),
                        roadblock_ids=[s for s in re.split(r"[\s,]+", str(r["roadblock_ids"] or "")) if s])
            for r in rows
        ]

    def _read_frames(self) -> list[LidarFrame]:
        rows = self._select("lidar_pc", _REQUIRED["lidar_pc"], "WHERE lidar_token = ? ORDER BY timestamp, token",
                            (bytes.fromhex(self.lidar.token),))
        frames = []
        for i, r in enumerate(rows):
            token = self._token(r["token"], "lidar_pc.token")
            if r["timestamp"] is None or r["filename"] is None:
                raise SchemaError(self.path, f"lidar_pc {token} has a NULL timestamp or filename")
            frames.append(LidarFrame(
                token=token, timestamp_us=int(r["timestamp"]), filename=str(r["filename"]),
                scene_token=self._hex(r["scene_token"], "lidar_pc.scene_token") or "",
                ego_pose_token=self._hex(r["ego_pose_token"], "lidar_pc.ego_pose_token") or "",
                lidar_token=self.lidar.token,
                prev_token=self._hex(r["prev_token"], "lidar_pc.prev_token"),
                next_token=self._hex(r["next_token"], "lidar_pc.next_token"), index=i,
            ))
        return frames

    def _read_images(self) -> list[ImageRecord]:
        if "image" not in self._columns:
            return []
        rows = self._select("image", ("token", "timestamp", "filename_jpg", "camera_token", "ego_pose_token",
                                      "prev_token", "next_token"), "ORDER BY timestamp, token")
        return [
            ImageRecord(token=self._token(r["token"], "image.token"), timestamp_us=int(r["timestamp"] or 0),
                        filename_jpg=str(r["filename_jpg"] or ""),
                        camera_token=self._hex(r["camera_token"], "image.camera_token") or "",
                        ego_pose_token=self._hex(r["ego_pose_token"], "image.ego_pose_token") or "",
                        prev_token=self._hex(r["prev_token"], "image.prev_token"),
                        next_token=self._hex(r["next_token"], "image.next_token"))
            for r in rows
        ]

    @cached_property
    def tracks(self) -> dict[str, TrackRecord]:
        """track token -> TrackRecord. SchemaError if a track's category is unknown or not one of
        NUPLAN_CATEGORIES (read on first use, so a log with bad labels still gives poses and points)."""
        names = {self._token(r["token"], "category.token"): r["name"] for r in self._select("category", ("token", "name"))}
        tracks = {}
        for r in self._select("track", ("token", "category_token", "width", "length", "height")):
            token = self._token(r["token"], "track.token")
            category = names.get(self._hex(r["category_token"], "track.category_token"))
            if category not in NUPLAN_CATEGORIES:
                raise SchemaError(self.path, f"track {token} has unknown category {category!r}; "
                                             f"expected one of {', '.join(NUPLAN_CATEGORIES)}")
            tracks[token] = TrackRecord(token=token, category=category, width=float(r["width"] or 0.0),
                                        length=float(r["length"] or 0.0), height=float(r["height"] or 0.0))
        return tracks

    # ------------------------------------------------------------------ public queries
    def frames_of_scene(self, scene_token: str) -> list[LidarFrame]:
        """The frames (time order) whose lidar_pc.scene_token is scene_token."""
        return list(self._frames_by_scene.get(scene_token, []))

    def ego_pose_at(self, timestamp_us: int) -> np.ndarray:
        """T_global_from_ego (4, 4) at a time (µs): slerp of rotation and linear translation between the two
        ego_pose rows around it; the first/last pose before/after the table's time range."""
        n = len(self._pose_times)
        if n == 0:
            raise SchemaError(self.path, "table ego_pose has no row")
        i = int(np.searchsorted(self._pose_times, timestamp_us, side="right"))
        if i == 0 or i == n:
            k = 0 if i == 0 else n - 1
            return make_transform(quaternion_to_matrix(self._pose_q[k]), self._pose_xyz[k])
        t0, t1 = self._pose_times[i - 1], self._pose_times[i]
        alpha = float(timestamp_us - t0) / float(t1 - t0)
        q = slerp(self._pose_q[i - 1], self._pose_q[i], alpha)
        xyz = (1.0 - alpha) * self._pose_xyz[i - 1] + alpha * self._pose_xyz[i]
        return make_transform(quaternion_to_matrix(q), xyz)

    def frame_pose(self, frame: LidarFrame) -> np.ndarray:
        """T_global_from_ego (4, 4) at the frame's lidar_pc timestamp."""
        return self.ego_pose_at(frame.timestamp_us)

    def _has_box_index(self) -> bool:
        for index in self._db.execute("PRAGMA index_list(lidar_box)").fetchall():
            name = index["name"].replace('"', '""')
            first = self._db.execute(f'PRAGMA index_info("{name}")').fetchone()
            if first is not None and first["name"] == "lidar_pc_token":
                return True
        return False

    def _box_rows(self, frame: LidarFrame) -> list[sqlite3.Row]:
        """lidar_box rows of a frame: per-frame query if lidar_pc_token is indexed, else one sorted bulk read."""
        key = bytes.fromhex(frame.token)
        if self._box_cache is None:
            if self._has_box_index():
                return self._select("lidar_box", _BOX_COLUMNS, "WHERE lidar_pc_token = ? ORDER BY token", (key,))
            rows = self._select("lidar_box", _BOX_COLUMNS, "ORDER BY lidar_pc_token, token")
            self._box_cache = {k: list(g) for k, g in groupby(rows, key=lambda r: r["lidar_pc_token"])}
        return self._box_cache.get(key, [])

    def boxes(self, frame: LidarFrame, frame_name: str = "global") -> Boxes:
        """The frame's lidar_box rows as Boxes in "global" (as stored) or "ego" (at frame_pose(frame)).

        sizes are [length, width, height] m; yaws rad; velocities m/s (NULL -> 0). SchemaError on a box
        without a known track or with an unknown category.
        """
        if frame_name not in ("global", "ego"):
            raise ValueError(f"frame_name must be 'global' or 'ego', got {frame_name!r}")
        rows = self._box_rows(frame)
        tracks = self.tracks
        track_tokens = [self._hex(r["track_token"], "lidar_box.track_token") for r in rows]
        for r, track in zip(rows, track_tokens):
            if track not in tracks:
                raise SchemaError(self.path, f"lidar_box {self._hex(r['token'], 'lidar_box.token')} refers to "
                                             f"missing track {track}")
        values = np.array([[float(r[c]) if r[c] is not None else np.nan for c in _BOX_COLUMNS[3:]] for r in rows],
                          dtype=np.float64).reshape(-1, len(_BOX_COLUMNS) - 3)
        if np.isnan(values[:, :7]).any():
            raise SchemaError(self.path, f"lidar_box rows of frame {frame.token} have NULL position, size or yaw")
        boxes = Boxes(
            frame="global", centers=values[:, 0:3], sizes=values[:, 3:6], yaws=values[:, 6],
            velocities=np.nan_to_num(values[:, 7:10]), categories=[tracks[t].category for t in track_tokens],
            track_tokens=track_tokens, tokens=[self._token(r["token"], "lidar_box.token") for r in rows],
        )
        if frame_name == "ego":
            return boxes.transformed(invert_transform(self.frame_pose(frame)), "ego")
        return boxes

    def box_counts(self) -> dict[str, int]:
        """Number of lidar_box rows per category over the frames of the MergedPointCloud lidar."""
        rows = self._db.execute(
            "SELECT lb.track_token AS track, COUNT(*) AS n FROM lidar_box lb JOIN lidar_pc lp "
            "ON lp.token = lb.lidar_pc_token WHERE lp.lidar_token = ? GROUP BY lb.track_token",
            (bytes.fromhex(self.lidar.token),),
        ).fetchall()
        counts = dict.fromkeys(NUPLAN_CATEGORIES, 0)
        tracks = self.tracks
        for r in rows:
            track = self._hex(r["track"], "lidar_box.track_token")
            if track not in tracks:
                raise SchemaError(self.path, f"lidar_box rows refer to missing track {track}")
            counts[tracks[track].category] += int(r["n"])
        return counts

    def blob_path(self, frame: LidarFrame) -> Path:
        """Where the frame's PCD should be: sensor_root / lidar_pc.filename."""
        return self.sensor_root / frame.filename

    def load_points(self, frame: LidarFrame) -> PointCloud:
        """The frame's merged cloud in the "lidar" frame. MissingBlobError names the missing sensor_blobs
        folder, log folder or file; PointCloudError names a corrupt or unreadable file."""
        path = self.blob_path(frame)
        if not path.is_file():
            log_dir = self.sensor_root / Path(frame.filename).parts[0]
            if not self.sensor_root.is_dir():
                raise MissingBlobError(self.sensor_root, "sensor_blobs folder is missing")
            if not log_dir.is_dir():
                raise MissingBlobError(log_dir, "sensor_blobs folder of this log is missing")
            raise MissingBlobError(path, f"point cloud blob of lidar_pc {frame.token} is missing")
        try:
            buf = path.read_bytes()
        except OSError as exc:
            raise PointCloudError(path, f"cannot read point cloud blob ({exc})") from None
        return read_pcd(buf, str(path))


def points_to_ego(cloud: PointCloud, log: NuplanLog) -> PointCloud:
    """A "lidar"-frame cloud of this log in the "ego" frame (rear axle), via log.lidar.T_ego_from_lidar."""
    if cloud.frame != "lidar":
        raise ValueError(f"points_to_ego expects a 'lidar'-frame cloud, got {cloud.frame!r}")
    return cloud.transformed(log.lidar.T_ego_from_lidar, "ego")


def points_to_global(cloud: PointCloud, log: NuplanLog, frame: LidarFrame) -> PointCloud:
    """A "lidar"- or "ego"-frame cloud of `frame` in the "global" frame, at log.frame_pose(frame)."""
    ego = points_to_ego(cloud, log) if cloud.frame == "lidar" else cloud
    if ego.frame != "ego":
        raise ValueError(f"points_to_global expects a 'lidar' or 'ego' cloud, got {cloud.frame!r}")
    return ego.transformed(log.frame_pose(frame), "global")
