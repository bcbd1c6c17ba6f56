"""A release frame's identity from the nuPlan log DBs, found by its lidar_pc token.

A folder named by a scene token is matched to its log through the DBs' `scene` tables; otherwise the
DBs are searched for the folder's first token. One log is open at a time (folders of one log are
usually consecutive). Poses are the logged ones (`NuplanLog.frame_pose`, interpolated at the lidar_pc
timestamp), not our refined poses.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

import numpy as np

from nuplan_occ.io.data_root import resolve_logs, sensor_root_for
from nuplan_occ.io.errors import NuplanFormatError, PoseGapError
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.pipeline.frame_columns import agent_speed_columns
from nuplan_occ.pipeline.scene import log_id_of

SPEED_WINDOW_US = 50_000
"""Half-width of the central difference of logged poses behind `ego_speed` (one 20 Hz sweep)."""


@dataclass
class FrameMeta:
    """What the logs say about one lidar_pc token. ego_to_global: T_global_from_ego (4, 4) at the
    sweep's timestamp; T_ego_from_lidar: the MergedPointCloud extrinsic; columns: ego_speed (m/s; NaN where the log has no usable pose around the frame),
    max_agent_speed (m/s), n_moving_agents, as our builds' filter columns."""

    log: str
    log_id: int
    scene_token: str | None
    scene_name: str | None
    frame_index: int
    timestamp_us: int
    ego_to_global: np.ndarray
    T_ego_from_lidar: np.ndarray
    columns: dict = field(default_factory=dict)


def _query(db: Path, sql: str, params: tuple = ()) -> list:
    connection = sqlite3.connect(f"file:{quote(str(db.resolve()))}?mode=ro", uri=True)
    try:
        return connection.execute(sql, params).fetchall()
    except sqlite3.DatabaseError:
        return []
    finally:
        connection.close()


class LogIndex:
    """Looks up lidar_pc tokens in the log DBs under a nuPlan data root (every `*.db` below it; a DB that
    cannot be read is left out, so its frames keep null identity). MissingLogError if there is none."""

    def __init__(self, logs_root: str | Path):
        self.root = Path(logs_root)
        self.dbs = resolve_logs(self.root, split=None)
        self._scene_db: dict[str, Path] | None = None
        self._token_db: dict[str, Path] = {}
        self._open: tuple[NuplanLog, dict, dict] | None = None

    def close(self) -> None:
        """Close the open log."""
        if self._open is not None:
            self._open[0].close()
            self._open = None

    def _db_of_scene(self, scene_token: str) -> Path | None:
        if self._scene_db is None:
            self._scene_db = {bytes(row[0]).hex(): db for db in self.dbs
                              for row in _query(db, "SELECT token FROM scene") if isinstance(row[0], bytes)}
        return self._scene_db.get(scene_token)

    def _db_of_token(self, token: bytes) -> Path | None:
        if token.hex() in self._token_db:
            return self._token_db[token.hex()]
        return next((db for db in self.dbs if _query(db, "SELECT 1 FROM lidar_pc WHERE token = ? LIMIT 1", (token,))),
                    None)

    def order_by_log(self, paths: Sequence[Path]) -> list[Path]:
        """`paths` (named `<lidar_pc token>.<ext>`) reordered so each log's frames are consecutive, in
        DB order and time order within a log; tokens no DB has come last, by name. Used for the dense
        layout, whose one folder mixes every log (one log is open at a time)."""
        by_token = {p.stem: p for p in paths}
        ordered = []
        for db in self.dbs:
            start = len(ordered)
            for (token,) in _query(db, "SELECT token FROM lidar_pc ORDER BY timestamp"):
                path = by_token.pop(token.hex(), None) if isinstance(token, bytes) else None
                if path is not None:
                    ordered.append(path)
            if len(ordered) > start:
                self._token_db[ordered[start].stem] = db  # the group's first lookup needs no DB search
        return ordered + sorted(by_token.values())

    def _load(self, db: Path) -> bool:
        """Open `db` as the current log; False (and the DB left out from then on) if it cannot be read."""
        self.close()
        try:
            log = NuplanLog(db, sensor_root_for(db, self.root))
        except NuplanFormatError:
            self.dbs = [d for d in self.dbs if d != db]
            return False
        self._open = (log, {f.token: f for f in log.frames}, {s.token: s.name for s in log.scenes})
        return True

    def lookup(self, token: str, folder: str) -> FrameMeta | None:
        """The logs' metadata of lidar_pc `token` (release folder name `folder`), None if no DB has it."""
        if self._open is None or token not in self._open[1]:
            try:
                key = bytes.fromhex(token)
            except ValueError:
                return None
            db = self._db_of_scene(folder) or self._db_of_token(key)
            if db is None or not self._load(db) or token not in self._open[1]:
                return None
        log, frames, scene_names = self._open
        frame = frames[token]
        name = log.meta.logfile or log.path.stem
        t = frame.timestamp_us
        try:
            before, after = log.ego_pose_at(t - SPEED_WINDOW_US), log.ego_pose_at(t + SPEED_WINDOW_US)
            ego_speed = float(np.linalg.norm((after[:2, 3] - before[:2, 3])) / (2e-6 * SPEED_WINDOW_US))
        except PoseGapError:  # the log has no usable pose around the frame: the speed is unknown
            ego_speed = float("nan")
        return FrameMeta(log=name, log_id=log_id_of(name), scene_token=frame.scene_token or None,
                         scene_name=scene_names.get(frame.scene_token), frame_index=frame.index, timestamp_us=t,
                         ego_to_global=log.frame_pose(frame), T_ego_from_lidar=log.lidar.T_ego_from_lidar,
                         columns={"ego_speed": ego_speed, **self._agent_columns(log, frame)})

    @staticmethod
    def _agent_columns(log: NuplanLog, frame) -> dict:
        """max_agent_speed and n_moving_agents of the frame's boxes; none (null) if its boxes are unreadable."""
        try:
            return agent_speed_columns(log.boxes(frame))
        except NuplanFormatError:
            return {}
