"""Repairs of auto-labelled tracks before refinement: headings turned by 180 deg, tracks split by an id switch,
tracks missing for a few sweeps, two tracks on one object, and boxes with no object in them (pure numpy).

Boxes are `nuplan_occ.io.types.Boxes` of one scene's sweeps in one frame shared by all of them (the stored
"global" frame); times in seconds. A repaired scene keeps every input box except the duplicates' and the
empty tracks'; it adds interpolated boxes in a track's short gaps (their lidar_box token is
"<track>@<sweep index>"). Each repair is off when its threshold is 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from nuplan_occ.geometry import invert_transform, wrap_angle
from nuplan_occ.io.types import Boxes


@dataclass(frozen=True)
class TrackRepairParams:
    """heading_window_s: half window (s) over which a moving track's box centres give its heading (a box turned
    by more than 90 deg from it is turned by 180 deg; a track that does not travel 1 m in the window takes the
    vote of all its boxes; 0: off). link_max_gap_s / link_max_distance_m: a track that
    starts at most this long after another of its category ended, within this distance of where the other's
    last box and velocity put it, continues it (0: off). fill_max_gap_s: a track's missing sweeps are filled by
    interpolation across gaps up to this long (0: off). duplicate_distance_m: a track whose boxes all lie within
    this distance (and half the narrower box's width: two bodies cannot be closer) of another track's (same
    category, same sweeps) and has fewer boxes is dropped (0: off)."""

    heading_window_s: float = 1.0
    link_max_gap_s: float = 1.0
    link_max_distance_m: float = 1.0
    fill_max_gap_s: float = 1.0
    duplicate_distance_m: float = 0.6


@dataclass
class RepairLog:
    """What `repair_tracks` changed: flipped boxes per track, renamed tracks (new -> continued), boxes added
    per track, tracks dropped as duplicates (dropped -> kept)."""

    flipped: dict[str, int] = field(default_factory=dict)
    linked: dict[str, str] = field(default_factory=dict)
    filled: dict[str, int] = field(default_factory=dict)
    duplicates: dict[str, str] = field(default_factory=dict)


@dataclass
class _Track:
    frames: list[int]
    centers: list[np.ndarray]
    yaws: list[float]
    sizes: list[np.ndarray]
    velocities: list[np.ndarray]
    category: str
    tokens: list[str]


def _tracks_of(boxes: list[Boxes]) -> dict[str, _Track]:
    tracks: dict[str, _Track] = {}
    for f, b in enumerate(boxes):
        for k, token in enumerate(b.track_tokens):
            t = tracks.setdefault(token, _Track([], [], [], [], [], b.categories[k], []))
            t.frames.append(f)
            t.centers.append(np.asarray(b.centers[k], np.float64))
            t.yaws.append(float(b.yaws[k]))
            t.sizes.append(np.asarray(b.sizes[k], np.float64))
            t.velocities.append(np.asarray(b.velocities[k], np.float64))
            t.tokens.append(b.tokens[k])
    return tracks


def voted_headings(yaws: np.ndarray, times: np.ndarray, window_s: float, centers: np.ndarray | None = None,
                   min_travel_m: float = 1.0) -> np.ndarray:
    """(n,) each box's yaw turned by 180 deg where it lies more than 90 deg from its track's heading there: the
    direction the box centres travel over +-window_s where they travel at least min_travel_m (centers (n, 3)
    given), else the vote of all the track's boxes: the axis of their yaws (mean of the doubled angles),
    pointed the way the sum of their unit headings points. yaws (n,) rad and times (n,) s (ascending) of one
    track's boxes."""
    yaws, times = np.asarray(yaws, np.float64), np.asarray(times, np.float64)
    axis = 0.5 * np.arctan2(np.sin(2 * yaws).sum(), np.cos(2 * yaws).sum())
    heading = np.full(len(yaws), axis if np.cos(yaws - axis).sum() >= 0 else axis + np.pi)
    if centers is not None and len(yaws):
        lo = np.searchsorted(times, times - window_s, side="left")
        hi = np.searchsorted(times, times + window_s, side="right") - 1
        travel = np.asarray(centers, np.float64)[hi, :2] - np.asarray(centers, np.float64)[lo, :2]
        moving = np.linalg.norm(travel, axis=1) >= min_travel_m
        heading = np.where(moving, np.arctan2(travel[:, 1], travel[:, 0]), heading)
    turned = np.cos(yaws - heading) < 0
    return np.where(turned, np.asarray(wrap_angle(yaws + np.pi), np.float64), yaws)


def _link(tracks: dict[str, _Track], times: np.ndarray, params: TrackRepairParams, log: RepairLog) -> None:
    order = sorted(tracks, key=lambda token: tracks[token].frames[0])
    for token in order:
        later = tracks.get(token)
        if later is None:
            continue
        start = times[later.frames[0]]
        best, best_distance = None, params.link_max_distance_m
        for other, earlier in tracks.items():
            if other == token or earlier.category != later.category or earlier.frames[-1] >= later.frames[0]:
                continue
            gap = start - times[earlier.frames[-1]]
            if gap > params.link_max_gap_s:
                continue
            predicted = earlier.centers[-1] + earlier.velocities[-1] * gap
            distance = float(np.linalg.norm(predicted[:2] - later.centers[0][:2]))
            if distance <= best_distance:
                best, best_distance = other, distance
        if best is not None:
            kept = tracks[best]
            for name in ("frames", "centers", "yaws", "sizes", "velocities", "tokens"):
                getattr(kept, name).extend(getattr(later, name))
            del tracks[token]
            log.linked[token] = best


def _fill(track_token: str, track: _Track, times: np.ndarray, max_gap_s: float, log: RepairLog) -> None:
    added = 0
    for a in range(len(track.frames) - 1, 0, -1):
        f0, f1 = track.frames[a - 1], track.frames[a]
        if f1 - f0 < 2 or times[f1] - times[f0] > max_gap_s:
            continue
        c0, c1, v0, v1 = track.centers[a - 1], track.centers[a], track.velocities[a - 1], track.velocities[a]
        y0, dyaw, size = track.yaws[a - 1], float(wrap_angle(track.yaws[a] - track.yaws[a - 1])), track.sizes[a - 1]
        for f in range(f1 - 1, f0, -1):
            w = (times[f] - times[f0]) / (times[f1] - times[f0])
            track.frames.insert(a, f)
            track.centers.insert(a, (1 - w) * c0 + w * c1)
            track.yaws.insert(a, float(wrap_angle(y0 + w * dyaw)))
            track.sizes.insert(a, size.copy())
            track.velocities.insert(a, (1 - w) * v0 + w * v1)
            track.tokens.insert(a, f"{track_token}@{f}")
            added += 1
    if added:
        log.filled[track_token] = added


def _duplicates(tracks: dict[str, _Track], distance_m: float, log: RepairLog) -> None:
    for token in sorted(tracks, key=lambda t: len(tracks[t].frames)):
        short = tracks[token]
        where = dict(zip(short.frames, short.centers))
        for other, long in tracks.items():
            if other == token or long.category != short.category or len(long.frames) < len(short.frames):
                continue
            common = [(where[f], c) for f, c in zip(long.frames, long.centers) if f in where]
            reach = min(distance_m, 0.5 * float(np.min([sz[1] for sz in short.sizes + long.sizes])))
            if len(common) == len(short.frames) and all(np.linalg.norm(a[:2] - b[:2]) <= reach for a, b in common):
                log.duplicates[token] = other
                break
        if token in log.duplicates:
            del tracks[token]


def repair_tracks(boxes: list[Boxes], times: np.ndarray, params: TrackRepairParams) -> tuple[list[Boxes], RepairLog]:
    """The sweeps' boxes (one Boxes per sweep, all in one frame; times (F,) s) repaired in this order: headings
    voted per track, id switches linked, duplicates dropped, gaps filled (see TrackRepairParams). Sweeps keep
    their boxes' order; added boxes come after them."""
    log = RepairLog()
    times = np.asarray(times, np.float64)
    tracks = _tracks_of(boxes)
    if params.heading_window_s > 0:
        for token, track in tracks.items():
            voted = voted_headings(np.array(track.yaws), times[track.frames], params.heading_window_s,
                                   np.array(track.centers))
            turned = int(np.count_nonzero(voted != np.array(track.yaws)))
            if turned:
                track.yaws = list(voted)
                log.flipped[token] = turned
    if params.link_max_gap_s > 0 and params.link_max_distance_m > 0:
        _link(tracks, times, params, log)
    if params.duplicate_distance_m > 0:
        _duplicates(tracks, params.duplicate_distance_m, log)
    if params.fill_max_gap_s > 0:
        for token, track in tracks.items():
            _fill(token, track, times, params.fill_max_gap_s, log)
    per_frame: list[list[tuple]] = [[] for _ in boxes]
    for token, t in tracks.items():
        for f, c, y, s, v, box_token in zip(t.frames, t.centers, t.yaws, t.sizes, t.velocities, t.tokens):
            per_frame[f].append((box_token, token, t.category, c, y, s, v))
    out = []
    for f, b in enumerate(boxes):
        rank = {token: k for k, token in enumerate(b.tokens)}
        rows = sorted(per_frame[f], key=lambda r: (rank.get(r[0], len(rank)), r[0]))
        if not rows:
            out.append(Boxes.empty(b.frame))
            continue
        out.append(Boxes(b.frame, np.array([r[3] for r in rows]), np.array([r[5] for r in rows]),
                         np.array([r[4] for r in rows], np.float64), np.array([r[6] for r in rows]),
                         [r[2] for r in rows], [r[1] for r in rows], [r[0] for r in rows]))
    return out, log


def repaired_sweeps(sweeps: list, params: TrackRepairParams) -> tuple[list, RepairLog]:
    """A scene's sweeps (nuplan_occ.pipeline.scene.Sweep, time order) with their stored boxes repaired by
    `repair_tracks` (boxes_global) and moved into each sweep's ego frame with its logged pose (boxes)."""
    times = np.array([s.timestamp_us for s in sweeps], np.float64) / 1e6
    repaired, log = repair_tracks([s.boxes_global for s in sweeps], times, params)
    return [replace(s, boxes_global=b, boxes=b.transformed(invert_transform(s.logged_pose), "ego"))
            for s, b in zip(sweeps, repaired)], log


def empty_tracks(box_frame_points: dict[str, list[np.ndarray]], heights: dict[str, float], clearance_m: float,
                 min_points: int, min_share: float = 0.0) -> set[str]:
    """Tracks whose boxes hold fewer than min_points points higher than clearance_m (at most a third of the box's
    height, so that a low object's own points count) above their box's bottom over all their sweeps, or fewer than
    min_share of all the points its boxes hold: boxes on nothing (a false-positive box on the road holds road
    points, and at most a stray return above them), while a far object seen by a handful of returns keeps them.
    box_frame_points: track -> its points (n, 3) per sweep, box frame (z = 0 at the box centre); heights:
    track -> box height (m)."""
    empty = set()
    for track, views in box_frame_points.items():
        floor = -heights[track] / 2.0 + min(clearance_m, heights[track] / 3.0)
        above = sum(int(np.count_nonzero(p[:, 2] > floor)) for p in views if len(p))
        total = sum(len(p) for p in views)
        if above < min_points or above < min_share * total:
            empty.add(track)
    return empty


def track_views(boxes: dict[int, Boxes], points: dict[int, dict[str, tuple]]) -> dict[str, list[np.ndarray]]:
    """track -> its box-frame points per sweep, from sweep -> Boxes and sweep -> track -> (points, ...)."""
    views: dict[str, list[np.ndarray]] = {}
    for i, b in boxes.items():
        for track in b.track_tokens:
            views.setdefault(track, []).append(points[i].get(track, (np.zeros((0, 3)),))[0])
    return views


def track_heights(boxes: dict[int, Boxes]) -> dict[str, float]:
    """track -> the median height (m) of its boxes, from sweep -> Boxes."""
    heights: dict[str, list[float]] = {}
    for b in boxes.values():
        for track, size in zip(b.track_tokens, b.sizes):
            heights.setdefault(track, []).append(float(size[2]))
    return {track: float(np.median(h)) for track, h in heights.items()}


def without_tracks(boxes: Boxes, tracks: set[str]) -> Boxes:
    """The boxes of tracks not in `tracks`."""
    if not tracks:
        return boxes
    return boxes.subset(np.array([t not in tracks for t in boxes.track_tokens], dtype=bool))
