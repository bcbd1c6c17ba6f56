"""`FrameRecord`, the unit the writer stores, and the frame key that names its tar members."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

STATUS_OK = "ok"
STATUS_FAILED = "failed"

_UNSAFE = re.compile(r"[^A-Za-z0-9_-]")
_UNSAFE_TOKEN = re.compile(r"[^A-Za-z0-9_]")


@dataclass
class FrameRecord:
    """One output frame of a log.

    Identity fields other than `token` may be None when the source does not say (an imported release
    without its nuPlan logs): the manifest stores null, never a guess. `ego_to_global`: (4, 4) float64, T_global_from_ego (ego = rear axle at `timestamp_us`, global = the
    map's UTM frame). `arrays`: any of the members in `nuplan_occ.storage.codecs.MEMBERS`, indexed
    [x, y, z] in that ego frame (`flow` in m/s, ego frame). `columns`: extra scalar manifest columns.
    A failed frame (`status="failed"`) carries no arrays, only its `failure_reason`.
    """

    log: str | None
    log_id: int | None
    scene_token: str | None
    scene_name: str | None
    frame_index: int | None
    token: str
    timestamp_us: int | None
    ego_to_global: np.ndarray | None
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    columns: dict[str, float | int | bool | str] = field(default_factory=dict)
    status: str = STATUS_OK
    failure_reason: str = ""

    @property
    def key(self) -> str:
        """The frame's WebDataset key: `frame_key`, or `token_key` when log or frame_index is unknown."""
        if self.log is None or self.frame_index is None:
            return token_key(self.token)
        return frame_key(self.log, self.frame_index)


def frame_key(log: str, frame_index: int) -> str:
    """`{log}-{frame_index:06d}` with every character of `log` outside [A-Za-z0-9_-] replaced by "_".

    WebDataset splits a member name at the first dot of its base name into key and suffix, and nuPlan
    log names contain dots (`2021.05.12.22.00.38_veh-35_01008_01518`), so the key has none.
    """
    return f"{_UNSAFE.sub('_', log)}-{int(frame_index):06d}"


def token_key(token: str) -> str:
    """The key of a frame whose log or frame index is unknown: its token, characters outside
    [A-Za-z0-9_] replaced by "_" (no "-", so it never looks like a `frame_key`)."""
    return _UNSAFE_TOKEN.sub("_", token)
