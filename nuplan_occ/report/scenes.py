"""Per-scene figures of the report (pure numpy over the scene's rows): what the scene table sorts by."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from nuplan_occ.report.flags import FlagResult
from nuplan_occ.report.frames import BuildFrames

_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


def _finite(values: np.ndarray) -> np.ndarray:
    return values[np.isfinite(values)]


def _median(values: np.ndarray) -> float:
    finite = _finite(values)
    return float(np.median(finite)) if finite.size else float("nan")


def _max(values: np.ndarray) -> float:
    finite = _finite(values)
    return float(finite.max()) if finite.size else float("nan")


def _mean(values: np.ndarray) -> float:
    finite = _finite(values)
    return float(finite.mean()) if finite.size else float("nan")


def _unlabeled_sum(columns: dict, ok: np.ndarray) -> float:
    missing = np.clip(columns["qa_boxes_with_points"][ok] - columns["qa_boxes_labeled"][ok], 0, None)
    return float(_finite(missing).sum())


@dataclass(frozen=True)
class Figure:
    """A sortable column of the scene table: key, header, the columns it needs (NaN when the build lacks
    one), and reduce(scene columns, ok mask) -> the scene's value over its ok frames."""

    key: str
    header: str
    needs: tuple[str, ...]
    reduce: Callable[[dict, np.ndarray], float]

    def value(self, columns: dict, ok: np.ndarray) -> float:
        return self.reduce(columns, ok) if all(n in columns for n in self.needs) else float("nan")


FIGURES = (
    Figure("pose_max", "pose corr. max (m)", ("qa_pose_correction_m",),
           lambda c, ok: _max(c["qa_pose_correction_m"][ok])),
    Figure("map_offset", "map offset (m)", ("qa_map_offset_m",), lambda c, ok: _median(c["qa_map_offset_m"][ok])),
    Figure("map_yaw", "map yaw |deg|", ("qa_map_yaw_deg",), lambda c, ok: _median(np.abs(c["qa_map_yaw_deg"][ok]))),
    Figure("observed", "observed frac. (median)", ("qa_lidar_observed_fraction",),
           lambda c, ok: _median(c["qa_lidar_observed_fraction"][ok])),
    Figure("coverage", "point coverage (median)", ("qa_point_coverage",),
           lambda c, ok: _median(c["qa_point_coverage"][ok])),
    Figure("occupied", "occupied voxels (mean)", ("qa_occupied_voxels",),
           lambda c, ok: _mean(c["qa_occupied_voxels"][ok])),
    Figure("unlabeled", "boxes w/o voxels (sum)", ("qa_boxes_with_points", "qa_boxes_labeled"), _unlabeled_sum),
    Figure("rays_agree", "rays agreeing (median)", ("qa_ray_agree",), lambda c, ok: _median(c["qa_ray_agree"][ok])),
    Figure("rays_early", "rays early (median)", ("qa_ray_early",), lambda c, ok: _median(c["qa_ray_early"][ok])),
)


@dataclass
class SceneSummary:
    """One scene of the build: identity, row range, frame counts, flagged frames per rule, figures, build
    seconds per frame (NaN without a build log) and stored KiB per ok frame."""

    page_id: str
    log: str
    scene: str
    scene_token: str
    start: int
    stop: int
    frames: int
    failed: int
    flagged: int
    flag_counts: dict[str, int]
    figures: dict[str, float]
    seconds_per_frame: float
    kib_per_frame: float
    stage_seconds: dict[str, float] = field(default_factory=dict)

    @property
    def href(self) -> str:
        """The scene page, relative to the report root."""
        return f"scenes/{self.page_id}/index.html"


def page_id(log: str, scene: str) -> str:
    """File-safe folder name of a scene's page: `<log>--<scene name>`, unsafe characters as '_'."""
    return _UNSAFE.sub("_", f"{log}--{scene}")


def summarize_scenes(frames: BuildFrames, flags: FlagResult, stage_seconds: dict[str, dict[str, float]]
                     ) -> list[SceneSummary]:
    """Every scene of `frames`, in its (log, scene name) order."""
    flagged_any = flags.flagged
    out = []
    c = frames.columns
    for start, stop in frames.scenes:
        rows = slice(start, stop)
        ok = frames.ok[rows]
        columns = {k: v[rows] for k, v in c.items()}
        token = str(c["scene_token"][start])
        seconds = stage_seconds.get(token, {})
        n = stop - start
        out.append(SceneSummary(
            page_id=page_id(str(c["log"][start]), str(c["scene_name"][start])), log=str(c["log"][start]),
            scene=str(c["scene_name"][start]), scene_token=token, start=start, stop=stop, frames=n,
            failed=int((~ok).sum()), flagged=int(flagged_any[rows].sum()),
            flag_counts={name: int(mask[rows].sum()) for name, mask in flags.masks.items()},
            figures={f.key: f.value(columns, ok) for f in FIGURES},
            seconds_per_frame=sum(seconds.values()) / n if seconds else float("nan"),
            kib_per_frame=float(columns["nbytes"][ok].mean() / 1024) if ok.any() else float("nan"),
            stage_seconds=seconds))
    return out
