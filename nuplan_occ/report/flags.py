"""The report's outlier rules: each flags frames of the manifest from its columns alone (pure numpy).

A rule whose columns the build lacks (an older build, a param that disabled the figure) is reported as not
evaluated, never as passed. Rules other than `failed` look at ok frames only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from nuplan_occ.rays.consistency import FLAG_RULES

POSE_CORRECTION_MAX_M = 0.5
"""A frame whose registration moved it further than this from the logged pose (m) is flagged."""

OBSERVED_FRACTION_OF_MEDIAN = 0.5
"""A frame whose LiDAR-observed fraction of the grid is below this share of the build's median is flagged."""

Columns = dict[str, np.ndarray]
"""Manifest columns as numpy arrays over the same frames (bool columns with nulls as False, numbers as float
with nulls as NaN, strings as object arrays with nulls as "")."""


@dataclass(frozen=True)
class Rule:
    """name: short id (CSS class, column of the scene table); title: what a curator reads; needs: the columns
    the rule reads; test(columns, ok) -> (frames,) bool, True where a frame is flagged."""

    name: str
    title: str
    needs: tuple[str, ...]
    test: Callable[[Columns, np.ndarray], np.ndarray]


def _failed(c: Columns, ok: np.ndarray) -> np.ndarray:
    return ~ok


def _pose_correction(c: Columns, ok: np.ndarray) -> np.ndarray:
    return ok & (c["qa_pose_correction_m"] > POSE_CORRECTION_MAX_M)


def _pose_rejected(c: Columns, ok: np.ndarray) -> np.ndarray:
    return ok & ~c["qa_pose_accepted"]


def _no_map(c: Columns, ok: np.ndarray) -> np.ndarray:
    return ok & (c["qa_map_status"] != "")


def _map_refused(c: Columns, ok: np.ndarray) -> np.ndarray:
    return ok & (c["qa_map_status"] == "") & ~c["qa_map_aligned"]


def build_median(values: np.ndarray, ok: np.ndarray) -> float:
    """Median of the finite values over ok frames (NaN with none)."""
    finite = values[ok & np.isfinite(values)]
    return float(np.median(finite)) if finite.size else float("nan")


def _low_observed(c: Columns, ok: np.ndarray) -> np.ndarray:
    values = c["qa_lidar_observed_fraction"]
    return ok & (values < OBSERVED_FRACTION_OF_MEDIAN * build_median(values, ok))


def _unlabeled_boxes(c: Columns, ok: np.ndarray) -> np.ndarray:
    return ok & (c["qa_boxes_with_points"] > c["qa_boxes_labeled"])


def _ray_rule(name: str) -> Rule:
    """The report's form of a ray-consistency flag rule (`rays.consistency.FLAG_RULES`, `nuplan-occ qa`)."""
    field, comparison, threshold = FLAG_RULES[name]
    column = f"qa_ray_{field}"
    what = {"early": "of a nearby sweep's LiDAR returns end more than 1 m early in the grid (floaters, ghosts, "
                     "doubled surfaces, trails)",
            "hole": "of a nearby sweep's LiDAR returns meet no occupied voxel where they hit a surface (holes)",
            "agree": "of a nearby sweep's LiDAR returns agree with the grid (the first occupied voxel on the ray "
                     "within a voxel of the return)"}
    title = f"{'more' if comparison == '>' else 'less'} than {threshold:.0%} {what[field]} ({column}; nuplan-occ qa)"
    return Rule(name, title, (column,), lambda c, ok: ok & ((c[column] > threshold) if comparison == ">"
                                                           else (c[column] < threshold)))


RULES = (
    Rule("failed", "frame failed to build (its reason is listed)", ("status",), _failed),
    Rule("pose", f"registration moved the frame more than {POSE_CORRECTION_MAX_M} m from its logged pose "
         "(qa_pose_correction_m)", ("qa_pose_correction_m",), _pose_correction),
    Rule("pose_rejected", "registration's ICP result was rejected, the logged pose kept (qa_pose_accepted)",
         ("qa_pose_accepted",), _pose_rejected),
    Rule("no_map", "no map used for labeling: ground is not split into road / line / other ground (qa_map_status)",
         ("qa_map_status",), _no_map),
    Rule("map_refused", "map-to-paint alignment refused: the map was drawn with the unaligned poses "
         "(qa_map_aligned false while a map was used)", ("qa_map_status", "qa_map_aligned"), _map_refused),
    Rule("low_observed", f"LiDAR-observed fraction of the grid below {OBSERVED_FRACTION_OF_MEDIAN:g} x the build's "
         "median (qa_lidar_observed_fraction)", ("qa_lidar_observed_fraction",), _low_observed),
    Rule("unlabeled_boxes", "a box with LiDAR points got no voxel (qa_boxes_with_points > qa_boxes_labeled)",
         ("qa_boxes_with_points", "qa_boxes_labeled"), _unlabeled_boxes),
    *(_ray_rule(name) for name in FLAG_RULES),
)


@dataclass
class FlagResult:
    """masks: rule name -> (frames,) bool for the evaluated rules; skipped: rule name -> why not evaluated;
    flagged: (frames,) True where any evaluated rule flags the frame."""

    masks: dict[str, np.ndarray]
    skipped: dict[str, str]
    flagged: np.ndarray


def evaluate_rules(columns: Columns, ok: np.ndarray, rules: tuple[Rule, ...] = RULES,
                   disabled: dict[str, str] | None = None) -> FlagResult:
    """Every rule over the frames; `disabled`: rule name -> why the build makes it meaningless (e.g. map
    alignment switched off by a param)."""
    masks, skipped = {}, dict(disabled or {})
    for rule in rules:
        if rule.name in skipped:
            continue
        missing = [name for name in rule.needs if name not in columns]
        if missing:
            skipped[rule.name] = f"column {', '.join(missing)} absent in this build"
            continue
        masks[rule.name] = np.asarray(rule.test(columns, ok), dtype=bool)
    flagged = np.zeros(len(ok), dtype=bool)
    for mask in masks.values():
        flagged |= mask
    return FlagResult(masks, skipped, flagged)
