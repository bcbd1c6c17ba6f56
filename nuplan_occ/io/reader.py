"""Reads one nuPlan log DB (SQLite) and its LiDAR blobs, without the devkit.

Frames (see nuplan_occ.io.types): "global" = map UTM metres; "ego" = rear axle at a frame's time;
"lidar" = frame of the DB's MergedPointCloud lidar row (T_ego_from_lidar = its stored extrinsic).
Timestamps are integer µs. Tokens are exposed as lowercase hex of whatever BLOB length the DB stores.

The DB is opened read-only and never written (no index is created in it); columns are selected by name
(extra columns are ignored), NULL chain ends become None. Large tables are read as columns, never as one
Python object per row: ego_pose at opening, image on first use, lidar_box one time window (a scene) per
query. A frame's pose is interpolated from the ego_pose table at the lidar_pc timestamp, because ego_pose
rows linked by token carry slightly different timestamps.

Every value is checked where it enters, and a bad one costs only what it touches:
- ego_pose rows with a NULL, non-finite or absurd position (beyond MAX_GLOBAL_COORD_M) or quaternion (norm
  off 1 by more than QUATERNION_NORM_TOLERANCE) are dropped and counted in `notes`; a frame whose time no
  usable rows bracket within POSE_GAP_LIMIT_US (or lies more than POSE_EDGE_LIMIT_US beyond the first or
  last one) gets no pose: PoseGapError, never an extrapolation;
- lidar_pc rows sharing a timestamp: the first in chain order (then token order) is used, the others get a
  `problem`; a filename that is absolute or holds '..' gets a `problem` and is never opened;
- lidar_box rows with a NULL, non-finite or absurd centre, size or yaw, or naming a missing track or a track
  of unknown category, fail the frames they belong to (SchemaError naming table, token and column);
- point clouds pass `nuplan_occ.io.pcd.usable_points`.
"""

from __future__ import annotations

import os
import re
import sqlite3
import threading
from functools import cached_property
from pathlib import Path, PurePosixPath
from urllib.parse import quote

import numpy as np

from nuplan_occ.geometry import invert_transform, make_transform, quaternion_to_matrix
from nuplan_occ.io.data_root import guess_sensor_root
from nuplan_occ.io.errors import (
    DatabaseError, MissingBlobError, OutsideDataRootError, PointCloudError, PoseGapError, SchemaError,
    UnsafePickleError,
)
from nuplan_occ.io.pcd import MAX_POINTS, DroppedPoints, read_pcd, usable_points
from nuplan_occ.io.pickles import load_calibration_blob
from nuplan_occ.io.types import (
    LIDAR_CHANNEL, NUPLAN_CATEGORIES, Boxes, CameraCalibration, EgoPoseTable, ImageTable, LidarCalibration,
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

_BOX_VALUES = ("x", "y", "z", "length", "width", "height", "yaw", "vx", "vy", "vz")
"""lidar_box value columns in the order Boxes takes them (centre, size, yaw, velocity)."""

MAX_GLOBAL_COORD_M = 1e7
"""|x| and |y| of an ego pose or box centre above this (m) are absurd: UTM eastings stay within 1e6 m and
northings within 1e7 m. |z| must stay within 1e4 m."""

QUATERNION_NORM_TOLERANCE = 0.01
"""An ego_pose quaternion is usable when its norm is within this of 1 (the DB stores unit quaternions)."""

MAX_BOX_SIZE_M = 100.0
"""A box side must be > 0 and at most this (m); the longest road vehicles are about 25 m."""

POSE_GAP_LIMIT_US = 100_000
"""A frame's pose is interpolated between the usable ego_pose rows around its time only when they are at most
0.1 s apart (ego_pose is logged at about 100 Hz: 10 rows missing). Linear interpolation over 0.1 s is off by
v^2 t^2 / (8 r): under 2 cm for 10 m/s on a 10 m radius."""

POSE_EDGE_LIMIT_US = 50_000
"""Before the first or after the last usable ego_pose row, a frame's pose is extrapolated from the two rows
at that end (constant velocity and turn rate) only up to 0.05 s: half a 10 Hz output period."""

_CHUNK_ROWS = 16_384
"""Rows fetched at a time from large tables read as columns."""

BOX_WINDOW_US = 10_000_000
"""`boxes(frame)` reads the boxes of this much time (µs) around the frame in one query and keeps them, so
walking a log frame by frame costs one table scan per window on a DB without a lidar_pc_token index."""


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions [w, x, y, z] (shortest arc); alpha in [0, 1] interpolates,
    outside it extrapolates along the same arc."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    q = (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)


def leaves_folder(name: str) -> bool:
    """True when a stored relative file name is absolute, holds a '..' part or a NUL byte: joined to a folder
    it could name a file outside it. (Symlinks inside the folder are followed: the user placed them.)"""
    if ".." not in name and "\x00" not in name and not name.startswith(("/", "\\")) and name[1:2] != ":":
        return False
    path = PurePosixPath(name.replace("\\", "/"))
    return "\x00" in name or path.is_absolute() or ".." in path.parts or bool(re.match(r"^[A-Za-z]:", name))


def _numeric(column: str) -> str:
    """SQL for a column's value when it is a number, else NULL (TEXT or BLOB in a FLOAT column)."""
    return f"CASE WHEN typeof({column}) IN ('integer', 'real') THEN {column} END"


class SceneBoxes:
    """The lidar_box rows of a set of frames, read in one query; `of(frame)` gives one frame's boxes.

    A frame with a bad row (see the module docstring) raises SchemaError for that frame only.
    """

    def __init__(self, by_frame: dict[str, Boxes], problems: dict[str, SchemaError]):
        self._by_frame = by_frame
        self._problems = problems

    def covers(self, frame: LidarFrame) -> bool:
        """True when the query included this frame."""
        return frame.token in self._by_frame or frame.token in self._problems

    def of(self, frame: LidarFrame) -> Boxes:
        """The frame's boxes in the "global" frame (sorted by token)."""
        if frame.token in self._problems:
            raise self._problems[frame.token]
        return self._by_frame.get(frame.token) or Boxes.empty("global")


class NuplanLog:
    """One nuPlan log DB plus its sensor_blobs folder. Use as a context manager (closes the DB).

    sensor_root: the folder that lidar_pc.filename is relative to; by default the first `sensor_blobs`
    (or `nuplan-v1.1/sensor_blobs`) folder found next to an ancestor of the DB, else
    `<db>/../../../sensor_blobs` (the released layout), which may not exist (load_points then raises).

    A lidar_pc row with a NULL scene_token gets scene_token "" (the devkit's synthetic DDL allows NULL).
    notes: one line per kind of row dropped at opening (e.g. unusable ego_pose rows), for the build to report.
    Point helpers: points_to_ego(cloud, log) and points_to_global(cloud, log, frame) below.

    Raises DatabaseError (missing, empty or non-SQLite file) and SchemaError (missing table/column/row, a
    non-BLOB token, a missing or duplicated MergedPointCloud lidar row, bad calibration) on opening.
    """

    def __init__(self, db_path: str | Path, sensor_root: str | Path | None = None):
        self.path = Path(db_path)
        if not self.path.is_file():
            raise DatabaseError(self.path, "log database file not found")
        if self.path.stat().st_size == 0:
            raise DatabaseError(self.path, "log database file is empty (0 bytes)")
        guessed = guess_sensor_root(self.path)
        self.sensor_root = Path(sensor_root) if sensor_root is not None else guessed
        try:
            self._db = sqlite3.connect(f"file:{quote(str(self.path.resolve()))}?mode=ro", uri=True)
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(self.path, f"cannot open SQLite database ({exc})") from None
        self._db.row_factory = sqlite3.Row
        self.notes: list[str] = []
        try:
            self._load()
        except BaseException:
            self._db.close()
            raise
        self._frames_by_scene: dict[str, list[LidarFrame]] = {}
        for frame in self.frames:
            self._frames_by_scene.setdefault(frame.scene_token, []).append(frame)
        self._window: SceneBoxes | None = None

    def _load(self) -> None:
        try:
            self._columns = self._read_columns()
        except sqlite3.DatabaseError as exc:
            raise DatabaseError(self.path, f"not a readable SQLite database ({exc})") from None
        try:
            self.meta = self._read_meta()
            self.lidar = self._read_lidar()
            self.cameras = self._read_cameras()
            self.ego_poses = self._read_ego_poses()
            self.scenes = self._read_scenes()
            self.frames = self._read_frames()
        except sqlite3.DatabaseError as exc:
            raise SchemaError(self.path, f"query failed ({exc})") from None

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
        if not tables:
            raise DatabaseError(self.path, "log database holds no tables (an empty SQLite file)")
        columns = {t: {r["name"] for r in self._db.execute(f'PRAGMA table_info("{t}")')} for t in tables}
        for table, needed in _REQUIRED.items():
            if table not in columns:
                raise SchemaError(self.path, f"table {table} is missing")
            missing = [c for c in needed if c not in columns[table]]
            if missing:
                raise SchemaError(self.path, f"table {table} lacks column(s) {', '.join(missing)}")
        return columns

    def _column(self, table: str, name: str, numeric: bool = False) -> str:
        """SQL of a named column (NULL if the table lacks this optional column); numeric: NULL unless a number."""
        if name not in self._columns[table]:
            return f"NULL AS {name}"
        return f"{_numeric(name)} AS {name}" if numeric else name

    def _select(self, table: str, names: tuple[str, ...], tail: str = "", params: tuple = ()) -> list[sqlite3.Row]:
        """Rows of named columns; optional columns absent from the table come back as NULL."""
        cols = ", ".join(self._column(table, n) for n in names)
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

    def _read_ego_poses(self) -> EgoPoseTable:
        """The usable ego_pose rows as columns (see the module docstring); the others are counted in notes."""
        timestamp = "CASE WHEN typeof(timestamp) = 'integer' THEN timestamp END"
        values = ", ".join(_numeric(c) for c in ("x", "y", "z", "qw", "qx", "qy", "qz"))
        cursor = self._db.execute(f"SELECT token, {timestamp}, {values} FROM ego_pose ORDER BY timestamp, token")
        tables, token_chunks = [np.zeros((0, 8))], [np.zeros(0, dtype="U1")]
        while rows := cursor.fetchmany(_CHUNK_ROWS):  # chunks: no Python object per row of the whole table at once
            if any(not isinstance(r[0], bytes) or not r[0] for r in rows):
                raise SchemaError(self.path, "ego_pose.token holds a NULL or non-BLOB token")
            tables.append(np.array([r[1:] for r in rows], dtype=np.float64).reshape(-1, 8))
            token_chunks.append(np.array([r[0].hex() for r in rows], dtype=str))
        table = np.concatenate(tables)
        tokens = np.concatenate(token_chunks)
        del tables, token_chunks
        times, xyz, q = table[:, 0], table[:, 1:4], table[:, 4:8]
        with np.errstate(invalid="ignore"):
            norm = np.linalg.norm(q, axis=1)
            usable = (np.isfinite(table).all(axis=1) & (np.abs(xyz[:, :2]) <= MAX_GLOBAL_COORD_M).all(axis=1)
                      & (np.abs(xyz[:, 2]) <= 1e4) & (np.abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE))
        times_int = np.where(usable, times, 0).astype(np.int64)
        repeated = np.zeros(len(times), dtype=bool)
        kept = np.flatnonzero(usable)
        repeated[kept[1:]] = np.diff(times_int[kept]) == 0  # rows are in (time, token) order: keep the first
        if (~usable).any():
            self.notes.append(f"{self.path}: {int((~usable).sum())} of {len(times)} ego_pose rows dropped "
                              "(NULL, non-finite or absurd position or quaternion)")
        if repeated.any():
            self.notes.append(f"{self.path}: {int(repeated.sum())} ego_pose rows repeat a timestamp; the first "
                              "by token is used")
        keep = usable & ~repeated
        return EgoPoseTable(tokens=tokens[keep], timestamps_us=times_int[keep], xyz=xyz[keep].copy(),
                            quaternions=q[keep])  # as stored: slerp and quaternion_to_matrix normalise

    def _read_scenes(self) -> list[SceneRecord]:
        rows = self._select("scene", ("token", "name", "goal_ego_pose_token", "roadblock_ids"), "ORDER BY name")
        return [
            SceneRecord(token=self._token(r["token"], "scene.token"), name=str(r["name"]),
                        goal_ego_pose_token=self._hex(r["goal_ego_pose_token"], "scene.goal_ego_pose_token"),
                        roadblock_ids=[s for s in re.split(r"[\s,]+", str(r["roadblock_ids"] or "")) if s])
            for r in rows
        ]

    def _read_frames(self) -> list[LidarFrame]:
        """lidar_pc rows of the merged LiDAR in time order; rows sharing a timestamp in chain order (a row whose
        prev_token is another row of the same time comes after it), then token order."""
        rows = self._select("lidar_pc", _REQUIRED["lidar_pc"], "WHERE lidar_token = ? ORDER BY timestamp, token",
                            (bytes.fromhex(self.lidar.token),))
        untimed = [r for r in rows if not isinstance(r["timestamp"], int)]
        if untimed:
            self.notes.append(f"{self.path}: {len(untimed)} lidar_pc rows without an integer timestamp skipped")
            rows = [r for r in rows if isinstance(r["timestamp"], int)]
        ordered = []
        for start in range(len(rows)):
            if start and rows[start]["timestamp"] == rows[start - 1]["timestamp"]:
                continue
            end = start
            while end + 1 < len(rows) and rows[end + 1]["timestamp"] == rows[start]["timestamp"]:
                end += 1
            group = rows[start:end + 1]
            tokens = {r["token"] for r in group}
            ordered += sorted(group, key=lambda r: (r["prev_token"] in tokens, r["token"]))
        frames: list[LidarFrame] = []
        first_at_time = ""
        for i, r in enumerate(ordered):
            token = self._token(r["token"], "lidar_pc.token")
            filename = r["filename"]
            problem = ""
            repeated = i > 0 and r["timestamp"] == ordered[i - 1]["timestamp"]
            first_at_time = first_at_time if repeated else token
            if repeated:
                problem = (f"lidar_pc {token} repeats the timestamp {r['timestamp']} of lidar_pc "
                           f"{first_at_time}; the earlier row in chain order is used")
            elif not isinstance(filename, str) or not filename:
                problem = f"lidar_pc {token} has no filename"
            elif leaves_folder(filename):
                problem = (f"lidar_pc {token}: its filename leaves the sensor_blobs folder (absolute "
                           "or '..' path); not opened")
            frames.append(LidarFrame(
                token=token, timestamp_us=int(r["timestamp"]), filename=str(filename or ""),
                scene_token=self._hex(r["scene_token"], "lidar_pc.scene_token") or "",
                ego_pose_token=self._hex(r["ego_pose_token"], "lidar_pc.ego_pose_token") or "",
                lidar_token=self.lidar.token,
                prev_token=self._hex(r["prev_token"], "lidar_pc.prev_token"),
                next_token=self._hex(r["next_token"], "lidar_pc.next_token"), index=i, problem=problem,
            ))
        return frames

    @cached_property
    def images(self) -> ImageTable:
        """The image rows as columns (read on first use; empty without an image table)."""
        if "image" not in self._columns:
            return ImageTable(np.zeros(0, dtype=str), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=str),
                              np.zeros(0, dtype=bytes))
        rows = self._db.execute(f"SELECT token, camera_token, filename_jpg, {_numeric('timestamp')} FROM image "
                                "ORDER BY timestamp, token").fetchall()
        tokens = [np.array([r[k].hex() if isinstance(r[k], bytes) else "" for r in rows], dtype=str).reshape(-1)
                  for k in range(2)]
        filenames = np.array([str(r[2] or "").encode() for r in rows], dtype=bytes).reshape(-1)
        times = np.array([r[3] if r[3] is not None else -1 for r in rows], dtype=np.int64).reshape(-1)
        return ImageTable(tokens=tokens[0], timestamps_us=times, camera_tokens=tokens[1], filenames=filenames)

    @cached_property
    def _track_table(self) -> tuple[dict[str, TrackRecord], dict[str, str]]:
        """(usable tracks, track token -> problem of the others: unknown category)."""
        names = {self._token(r["token"], "category.token"): r["name"] for r in self._select("category", ("token", "name"))}
        tracks, problems = {}, {}
        for r in self._select("track", ("token", "category_token", "width", "length", "height")):
            token = self._token(r["token"], "track.token")
            category = names.get(self._hex(r["category_token"], "track.category_token"))
            if category not in NUPLAN_CATEGORIES:
                problems[token] = (f"track {token} has unknown category {category!r}; expected one of "
                                   f"{', '.join(NUPLAN_CATEGORIES)}")
                continue
            size = [r[c] if isinstance(r[c], (int, float)) else 0.0 for c in ("width", "length", "height")]
            tracks[token] = TrackRecord(token=token, category=category, width=float(size[0]),
                                        length=float(size[1]), height=float(size[2]))
        return tracks, problems

    @property
    def tracks(self) -> dict[str, TrackRecord]:
        """track token -> TrackRecord of the tracks with a known category (one of NUPLAN_CATEGORIES); a box of
        any other track fails its frame (read on first use, so a log with bad labels still gives poses and points)."""
        return self._track_table[0]

    # ------------------------------------------------------------------ public queries
    def frames_of_scene(self, scene_token: str) -> list[LidarFrame]:
        """The frames (time order) whose lidar_pc.scene_token is scene_token."""
        return list(self._frames_by_scene.get(scene_token, []))

    def ego_pose_at(self, timestamp_us: int) -> np.ndarray:
        """T_global_from_ego (4, 4) at a time (µs): slerp of rotation and linear translation between the two
        usable ego_pose rows around it, when at most POSE_GAP_LIMIT_US apart; up to POSE_EDGE_LIMIT_US before the
        first or after the last row, extrapolated along the two rows at that end. PoseGapError otherwise."""
        poses = self.ego_poses
        times = poses.timestamps_us
        n = len(times)
        if n == 0:
            raise PoseGapError(self.path, "table ego_pose has no usable row")
        i = int(np.searchsorted(times, timestamp_us, side="right"))
        if 0 < i < n:
            a, b = i - 1, i
        else:
            edge = 0 if i == 0 else n - 1
            beyond = abs(int(timestamp_us) - int(times[edge]))
            if beyond > POSE_EDGE_LIMIT_US:
                side = "before the first" if i == 0 else "after the last"
                raise PoseGapError(self.path, f"no pose at {timestamp_us} µs: {beyond / 1e3:.0f} ms {side} usable "
                                              f"ego_pose row (limit {POSE_EDGE_LIMIT_US / 1e3:.0f} ms)")
            if beyond == 0 or n == 1:
                return poses.T_global_from_ego(edge)
            a, b = (0, 1) if i == 0 else (n - 2, n - 1)
        if times[b] - times[a] > POSE_GAP_LIMIT_US:
            raise PoseGapError(self.path, f"no pose at {timestamp_us} µs: the usable ego_pose rows it lies between or "
                                          f"next to are {(times[b] - times[a]) / 1e3:.0f} ms apart (limit "
                                          f"{POSE_GAP_LIMIT_US / 1e3:.0f} ms)")
        alpha = float(timestamp_us - times[a]) / float(times[b] - times[a])
        q = slerp(poses.quaternions[a], poses.quaternions[b], alpha)
        xyz = (1.0 - alpha) * poses.xyz[a] + alpha * poses.xyz[b]
        return make_transform(quaternion_to_matrix(q), xyz)

    def nearest_pose(self, timestamp_us: int) -> np.ndarray:
        """T_global_from_ego (4, 4) of the usable ego_pose row nearest in time: a stand-in for a frame that gets
        no pose (never its pose). PoseGapError when the table has no usable row."""
        times = self.ego_poses.timestamps_us
        if not len(times):
            raise PoseGapError(self.path, "table ego_pose has no usable row")
        return self.ego_poses.T_global_from_ego(int(np.argmin(np.abs(times - timestamp_us))))

    def frame_pose(self, frame: LidarFrame) -> np.ndarray:
        """T_global_from_ego (4, 4) at the frame's lidar_pc timestamp (PoseGapError: see ego_pose_at)."""
        try:
            return self.ego_pose_at(frame.timestamp_us)
        except PoseGapError as exc:
            raise PoseGapError(self.path, f"lidar_pc {frame.token}: {exc.problem}") from None

    def scene_boxes(self, frames: list[LidarFrame]) -> SceneBoxes:
        """The boxes of `frames` (any frames of this log), in one query over the lidar_pc rows of their time span.

        The statement selects lidar_box rows whose lidar_pc_token is in that span (a list subquery): one pass
        over lidar_box without an index on lidar_pc_token, index lookups with one.
        """
        if not frames:
            return SceneBoxes({}, {})
        first = min(f.timestamp_us for f in frames)
        last = max(f.timestamp_us for f in frames)
        columns = ", ".join(self._column("lidar_box", c, numeric=True) for c in _BOX_VALUES)
        rows = self._db.execute(
            f"SELECT lidar_pc_token, token, track_token, {columns} FROM lidar_box WHERE lidar_pc_token IN "
            "(SELECT token FROM lidar_pc WHERE lidar_token = ? AND timestamp BETWEEN ? AND ?)",
            (bytes.fromhex(self.lidar.token), first, last)).fetchall()
        wanted = {bytes.fromhex(f.token) for f in frames}
        rows = sorted((r for r in rows if r[0] in wanted), key=lambda r: (r[0], r[1]))
        values = np.array([r[3:] for r in rows], dtype=np.float64).reshape(-1, len(_BOX_VALUES))
        bad = self._bad_box_values(values)
        tracks, track_problems = self._track_table
        by_frame: dict[str, Boxes] = {}
        problems: dict[str, SchemaError] = {}
        start = 0
        while start < len(rows):
            end = start
            while end + 1 < len(rows) and rows[end + 1][0] == rows[start][0]:
                end += 1
            frame_token = rows[start][0].hex()
            try:
                by_frame[frame_token] = self._frame_boxes(rows[start:end + 1], values[start:end + 1],
                                                          bad[start:end + 1], tracks, track_problems)
            except SchemaError as exc:
                problems[frame_token] = SchemaError(self.path, f"lidar_pc {frame_token}: {exc.problem}")
            start = end + 1
        for frame in frames:
            if frame.token not in by_frame and frame.token not in problems:
                by_frame[frame.token] = Boxes.empty("global")
        return SceneBoxes(by_frame, problems)

    @staticmethod
    def _bad_box_values(values: np.ndarray) -> np.ndarray:
        """(K, 7) True where a centre, size or yaw value is NULL, non-finite or absurd."""
        core = values[:, :7]
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(core)
            bad[:, :2] |= np.abs(core[:, :2]) > MAX_GLOBAL_COORD_M
            bad[:, 2] |= np.abs(core[:, 2]) > 1e4
            bad[:, 3:6] |= (core[:, 3:6] <= 0) | (core[:, 3:6] > MAX_BOX_SIZE_M)
        return bad

    def _frame_boxes(self, rows: list, values: np.ndarray, bad: np.ndarray, tracks: dict[str, TrackRecord],
                     track_problems: dict[str, str]) -> Boxes:
        """One frame's rows as global Boxes; SchemaError naming the first bad row, its column or its track."""
        tokens = [self._token(r[1], "lidar_box.token") for r in rows]
        track_tokens = [self._hex(r[2], "lidar_box.track_token") for r in rows]
        if bad.any():
            k, column = np.argwhere(bad)[0]
            value = values[k, column]
            what = "NULL or not a number" if np.isnan(value) else f"{value:g}, out of range"
            raise SchemaError(self.path, f"table lidar_box, token {tokens[k]}, column {_BOX_VALUES[column]}: {what}")
        for token, track in zip(tokens, track_tokens):
            if track in track_problems:
                raise SchemaError(self.path, f"table lidar_box, token {token}: {track_problems[track]}")
            if track not in tracks:
                raise SchemaError(self.path, f"table lidar_box, token {token}, column track_token: names missing "
                                             f"track {track}")
        velocities = values[:, 7:10]
        return Boxes(frame="global", centers=values[:, 0:3].copy(), sizes=values[:, 3:6].copy(),
                     yaws=values[:, 6].copy(), velocities=np.where(np.isfinite(velocities), velocities, 0.0),
                     categories=[tracks[t].category for t in track_tokens], track_tokens=track_tokens, tokens=tokens)

    def boxes(self, frame: LidarFrame, frame_name: str = "global") -> Boxes:
        """The frame's lidar_box rows as Boxes in "global" (as stored) or "ego" (at frame_pose(frame)).

        sizes are [length, width, height] m; yaws rad; velocities m/s (NULL -> 0). SchemaError on a bad row of
        this frame (see the module docstring). Reads BOX_WINDOW_US of boxes around the frame at once and keeps
        them; a scene's worth at a time is `scene_boxes`.
        """
        if frame_name not in ("global", "ego"):
            raise ValueError(f"frame_name must be 'global' or 'ego', got {frame_name!r}")
        if self._window is None or not self._window.covers(frame):
            half = BOX_WINDOW_US // 2
            self._window = self.scene_boxes([f for f in self.frames
                                             if abs(f.timestamp_us - frame.timestamp_us) <= half] or [frame])
        boxes = self._window.of(frame)
        if frame_name == "ego":
            return boxes.transformed(invert_transform(self.frame_pose(frame)), "ego")
        return boxes

    def box_counts(self) -> dict[str, int]:
        """Number of lidar_box rows per category over the frames of the MergedPointCloud lidar. SchemaError if
        a counted box names a missing track or one of unknown category."""
        rows = self._db.execute(
            "SELECT lb.track_token AS track, COUNT(*) AS n FROM lidar_box lb JOIN lidar_pc lp "
            "ON lp.token = lb.lidar_pc_token WHERE lp.lidar_token = ? GROUP BY lb.track_token",
            (bytes.fromhex(self.lidar.token),),
        ).fetchall()
        counts = dict.fromkeys(NUPLAN_CATEGORIES, 0)
        tracks, track_problems = self._track_table
        for r in rows:
            track = self._hex(r["track"], "lidar_box.track_token")
            if track in track_problems:
                raise SchemaError(self.path, track_problems[track])
            if track not in tracks:
                raise SchemaError(self.path, f"lidar_box rows refer to missing track {track}")
            counts[tracks[track].category] += int(r["n"])
        return counts

    def blob_path(self, frame: LidarFrame) -> Path:
        """Where the frame's PCD should be: sensor_root / lidar_pc.filename. OutsideDataRootError (naming the DB,
        not the file) when the filename is absolute or climbs out with '..'."""
        if leaves_folder(frame.filename):
            raise OutsideDataRootError(self.path, f"lidar_pc {frame.token}: its filename leaves the sensor_blobs "
                                                  "folder (absolute or '..' path); not opened")
        return self.sensor_root / frame.filename

    def load_sweep(self, frame: LidarFrame) -> tuple[PointCloud, DroppedPoints]:
        """The frame's usable points in the "lidar" frame (`nuplan_occ.io.pcd.usable_points`) and what was
        dropped. MissingBlobError names the missing sensor_blobs folder, log folder or file; PointCloudError a
        corrupt, oversized, empty or degenerate file; OutsideDataRootError a filename leaving sensor_blobs;
        a frame with a `problem` raises SchemaError with it."""
        path = self.blob_path(frame)
        if frame.problem:
            raise SchemaError(self.path, frame.problem)
        if not path.is_file():
            log_dir = self.sensor_root / Path(frame.filename).parts[0]
            if not self.sensor_root.is_dir():
                raise MissingBlobError(self.sensor_root, "sensor_blobs folder is missing")
            if not log_dir.is_dir():
                raise MissingBlobError(log_dir, "sensor_blobs folder of this log is missing")
            raise MissingBlobError(path, f"point cloud blob of lidar_pc {frame.token} is missing")
        try:
            size = path.stat().st_size
            if size > 64 * 1024 + 64 * MAX_POINTS:
                raise PointCloudError(path, f"point cloud blob of {size} bytes is larger than any sweep "
                                            f"of at most {MAX_POINTS} points")
            buf = path.read_bytes()
        except OSError as exc:
            raise PointCloudError(path, f"cannot read point cloud blob ({exc.strerror or exc})") from None
        return usable_points(read_pcd(buf, str(path)), str(path))

    def load_points(self, frame: LidarFrame) -> PointCloud:
        """The frame's usable points in the "lidar" frame; errors as load_sweep."""
        return self.load_sweep(frame)[0]


_open_logs: dict[str, tuple[tuple, NuplanLog]] = {}
"""The log this worker (process and thread) has open: its identity key and the reader."""


def open_log(db_path: str, sensor_root: str) -> NuplanLog:
    """The reader of a log DB, reused while the same process and thread asks for the same unchanged file
    (path, sensor root, inode, size and mtime); the previously open log is closed when another is asked for."""
    st = os.stat(db_path)
    key = (db_path, sensor_root, st.st_ino, st.st_size, st.st_mtime_ns)
    slot = f"{os.getpid()}:{threading.get_ident()}"
    held = _open_logs.get(slot)
    if held is not None and held[0] == key:
        return held[1]
    if held is not None:
        held[1].close()
    log = NuplanLog(db_path, sensor_root)
    _open_logs[slot] = (key, log)
    return log


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
