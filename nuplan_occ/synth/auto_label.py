"""Failures of auto-labelled boxes, applied to a synthetic log's tracks and per-frame boxes (no I/O).

nuPlan's lidar_box rows come from an offline auto-labeller; besides the Gaussian noise of `imperfect.noisy_boxes`
its boxes show: velocities that are estimates, boxes turned by 180 deg, tracks missing for a while, id switches,
boxes on nothing, boxes too small or too large for their object and two tracks on one object. Each failure is a
`SynthOptions` field (off by default; see there for its magnitude) and picks the boxed agents it hits by how near
they come to the ego (the nearest first, so the failure shows in the sweeps); no agent gets two failures. The
world, and so the truth, is never changed: every object stays where it is, whatever its boxes say.

Frames: boxes in "global" (UTM); agent states in the world's "local" frame; times in seconds from the log start.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon

from nuplan_occ.geometry import wrap_angle
from nuplan_occ.io.types import Boxes, LidarFrame, TrackRecord
from nuplan_occ.io.writer import new_token
from nuplan_occ.synth.agents import Agent
from nuplan_occ.synth.presets import SynthOptions
from nuplan_occ.synth.world import World

FRAME_S = 0.05
FALSE_POSITIVE_SIZE = (4.6, 1.9, 1.6)
"""[length, width, height] m of a false-positive vehicle box."""
FLIP_PARKED_REACH_M = 20.0
"""Flips go to parked vehicles that come this near the ego first (farther ones are mostly hidden by their
neighbours), then to the nearest vehicles."""
GAP_PAD_FRAMES = 5
"""A track gap keeps this many boxed frames before and after it where the track's span allows (a gap at a track's
end is a track that ends early)."""
_FAILURE_FIELDS = ("box_velocity_sigma", "yaw_flip_tracks", "gap_tracks", "id_switch_tracks", "false_positive_boxes",
                   "undersized_tracks", "oversized_tracks", "duplicate_tracks")


def has_label_failures(options: SynthOptions) -> bool:
    """Whether any auto-label failure is switched on."""
    return any(getattr(options, name) for name in _FAILURE_FIELDS)


@dataclass
class LabelFailures:
    """Which tracks each failure hit (track tokens as written; frame indices into the log's frames), for tests
    and reports: flipped {token: frames}, gaps {token: frames}, switched {old token: (new token, first frame)},
    false_positives {token: frames}, undersized / oversized [tokens], duplicated {original token: (duplicate
    token, frames)}."""

    flipped: dict
    gaps: dict
    switched: dict
    false_positives: dict
    undersized: list
    oversized: list
    duplicated: dict


def _replace_boxes(boxes: Boxes, keep: np.ndarray | None = None, extra: Boxes | None = None) -> Boxes:
    kept = boxes if keep is None else boxes.subset(keep)
    if extra is None:
        return kept
    return Boxes(kept.frame, np.concatenate([kept.centers, extra.centers]), np.concatenate([kept.sizes, extra.sizes]),
                 np.concatenate([kept.yaws, extra.yaws]), np.concatenate([kept.velocities, extra.velocities]),
                 kept.categories + extra.categories, kept.track_tokens + extra.track_tokens, kept.tokens + extra.tokens)


class _Log:
    """The boxes being edited, with where each track is boxed and how near it comes to the ego."""

    def __init__(self, world: World, boxed: list[Agent], tracks: list[TrackRecord], boxes: dict[str, Boxes],
                 frames: list[LidarFrame], true_poses: np.ndarray):
        self.world, self.boxed, self.tracks, self.boxes, self.frames = world, boxed, tracks, boxes, frames
        self.times = np.array([(f.timestamp_us - world.start_us) / 1e6 for f in frames])
        self.ego_xy = true_poses[:, :2, 3] - world.origin[:2]
        self.index = {t.token: k for k, t in enumerate(tracks)}
        self.present = np.zeros((len(boxed), len(frames)), dtype=bool)
        for f, frame in enumerate(frames):
            for token in boxes[frame.token].track_tokens:
                self.present[self.index[token], f] = True
        dist = np.array([np.linalg.norm(a.state(self.times)[0][:, :2] - self.ego_xy, axis=1) for a in boxed])
        self.dist = np.where(self.present, dist.reshape(len(boxed), len(frames)), np.inf)
        self.used: set[int] = set()

    def pick(self, n: int, *wanted: np.ndarray) -> list[int]:
        """Up to n unused boxed tracks, from each `wanted` mask in turn, nearest approach to the ego first."""
        closest = self.dist.min(axis=1)
        out: list[int] = []
        for want in wanted:
            for k in np.argsort(closest, kind="stable"):
                if len(out) < n and want[k] and np.isfinite(closest[k]) and k not in self.used and k not in out:
                    out.append(int(k))
        self.used.update(out)
        return out

    def kind(self, category: str, moving: bool | None = None) -> np.ndarray:
        return np.array([a.category == category and (moving is None or a.moving == moving) for a in self.boxed], bool)

    def window(self, k: int, seconds: float, pad: int = 0) -> np.ndarray:
        """round(seconds / FRAME_S) consecutive frames (indices) of track k centred as near its closest approach to
        the ego as its boxed frames allow, keeping `pad` boxed frames before and after it where the span allows
        (fewer frames, where it is boxed, if its boxed span is shorter)."""
        n = max(1, int(round(seconds / FRAME_S)))
        boxed = np.flatnonzero(self.present[k])
        first, last = boxed[0] + pad, boxed[-1] - pad - n + 1
        if last < first:
            first, last = boxed[0], max(boxed[0], boxed[-1] - n + 1)
        start = int(np.clip(int(np.argmin(self.dist[k])) - n // 2, first, last))
        frames = np.arange(start, min(start + n, len(self.frames)))
        return frames[self.present[k, frames]]

    def position(self, f: int, token: str) -> int:
        return self.boxes[self.frames[f].token].track_tokens.index(token)


def _scale_track(log: _Log, k: int, scale: float) -> None:
    track = log.tracks[k]
    track.length, track.width, track.height = track.length * scale, track.width * scale, track.height * scale
    for f in np.flatnonzero(log.present[k]):
        log.boxes[log.frames[f].token].sizes[log.position(f, track.token)] *= scale


def _flip_frames(count: int, share: float, run: int, rng: np.random.Generator) -> np.ndarray:
    """Positions (into a track's boxed frames, 0..count-1) covered by runs of `run` frames at random starts until
    share of them are covered."""
    flipped = np.zeros(count, dtype=bool)
    target = int(round(share * count))
    while flipped.sum() < target:
        start = int(rng.integers(count))
        flipped[start:start + run] = True
    return np.flatnonzero(flipped)


def _false_positive(log: _Log, options: SynthOptions, rng: np.random.Generator, attempts: int = 400) -> tuple[np.ndarray, float, np.ndarray] | None:
    """(local centre (3,), yaw, frames) of a vehicle box on drivable ground 10-30 m from the ego, where no agent
    nor the ego comes within 3 m of its footprint during its frames; None if no place was found."""
    n = max(1, int(round(options.false_positive_seconds / FRAME_S)))
    drivable = log.world.net.drivable
    length, width, _ = FALSE_POSITIVE_SIZE
    others = [(a, 0.5 * float(np.hypot(a.size[0], a.size[1]))) for a in log.world.agents]
    for _ in range(attempts):
        first = int(rng.integers(int(0.2 * len(log.frames)), max(int(0.8 * len(log.frames)) - n, int(0.2 * len(log.frames)) + 1)))
        frames = np.arange(first, min(first + n, len(log.frames)))
        bearing, distance = rng.uniform(-np.pi, np.pi), rng.uniform(10.0, 30.0)
        xy = log.ego_xy[first] + distance * np.array([np.cos(bearing), np.sin(bearing)])
        lanes = [heading for poly, heading, _, _ in log.world.net.lanes if poly.contains(shapely.Point(xy))]
        yaw = float(lanes[0]) if lanes else float(rng.uniform(-np.pi, np.pi))
        c, s = np.cos(yaw), np.sin(yaw)
        corners = xy + np.array([[c * u - s * v, s * u + c * v] for u, v in
                                 ((length / 2, width / 2), (-length / 2, width / 2), (-length / 2, -width / 2), (length / 2, -width / 2))])
        if not drivable.contains(Polygon(corners)):
            continue
        reach = 0.5 * float(np.hypot(length, width)) + 3.0
        if np.any(np.linalg.norm(log.ego_xy[frames] - xy, axis=1) < reach + 3.0):
            continue
        if any(np.any(np.linalg.norm(a.state(log.times[frames])[0][:, :2] - xy, axis=1) < reach + r) for a, r in others):
            continue
        return np.array([xy[0], xy[1], FALSE_POSITIVE_SIZE[2] / 2]), yaw, frames
    return None


def apply_label_failures(world: World, boxed: list[Agent], tracks: list[TrackRecord], boxes: dict[str, Boxes],
                         frames: list[LidarFrame], true_poses: np.ndarray, options: SynthOptions,
                         rng: np.random.Generator) -> tuple[list[TrackRecord], dict[str, Boxes], LabelFailures]:
    """The log's tracks and boxes (frame token -> global Boxes, track k of `tracks` annotating boxed[k]) with the
    auto-label failures of `options`; true_poses (F, 4, 4) TRUE T_global_from_ego of the frames. Edits the
    given boxes in place and returns (tracks incl. new ones, boxes, what was hit)."""
    hit = LabelFailures({}, {}, {}, {}, [], [], {})
    if not has_label_failures(options):
        return tracks, boxes, hit
    log = _Log(world, boxed, tracks, boxes, frames, true_poses)
    tracks = list(tracks)
    if options.box_velocity_sigma:
        for frame in frames:
            b = boxes[frame.token]
            b.velocities[:, :2] += options.box_velocity_sigma * rng.standard_normal((len(b), 2))
    for k in log.pick(options.undersized_tracks, log.kind("pedestrian"), log.kind("bicycle")):
        _scale_track(log, k, options.undersized_scale)
        hit.undersized.append(tracks[k].token)
    for k in log.pick(options.oversized_tracks, log.kind("vehicle", moving=False), log.kind("vehicle")):
        _scale_track(log, k, options.oversized_scale)
        hit.oversized.append(tracks[k].token)
    run = max(1, int(round(options.yaw_flip_run_s / FRAME_S)))
    parked_near = log.kind("vehicle", moving=False) & (log.dist.min(axis=1) <= FLIP_PARKED_REACH_M)
    for k in log.pick(options.yaw_flip_tracks, parked_near, log.kind("vehicle")):
        boxed_frames = np.flatnonzero(log.present[k])
        chosen = boxed_frames[_flip_frames(len(boxed_frames), options.yaw_flip_share, run, rng)]
        for f in chosen:
            b = boxes[frames[f].token]
            i = log.position(f, tracks[k].token)
            b.yaws[i] = float(wrap_angle(b.yaws[i] + np.pi))
        hit.flipped[tracks[k].token] = chosen
    for k in log.pick(options.gap_tracks, log.kind("vehicle", moving=True), np.array([a.moving for a in boxed], bool)):
        gap = log.window(k, options.gap_seconds, pad=GAP_PAD_FRAMES)
        for f in gap:
            b = boxes[frames[f].token]
            keep = np.ones(len(b), dtype=bool)
            keep[log.position(f, tracks[k].token)] = False
            boxes[frames[f].token] = _replace_boxes(b, keep)
        hit.gaps[tracks[k].token] = gap
    for k in log.pick(options.id_switch_tracks, log.kind("vehicle", moving=True), np.array([a.moving for a in boxed], bool)):
        boxed_frames = np.flatnonzero(log.present[k])
        old = tracks[k]
        new = TrackRecord(new_token(rng), old.category, old.width, old.length, old.height)
        tracks.append(new)
        first = int(boxed_frames[len(boxed_frames) // 2])
        for f in boxed_frames[boxed_frames >= first]:
            boxes[frames[f].token].track_tokens[log.position(f, old.token)] = new.token
        hit.switched[old.token] = (new.token, first)
    for k in log.pick(options.duplicate_tracks, log.kind("vehicle", moving=True)):
        old = tracks[k]
        twin = TrackRecord(new_token(rng), old.category, old.width, old.length, old.height)
        tracks.append(twin)
        window = log.window(k, options.duplicate_seconds)
        for f in window:
            b = boxes[frames[f].token]
            i = log.position(f, old.token)
            side = options.duplicate_offset_m * np.array([-np.sin(b.yaws[i]), np.cos(b.yaws[i]), 0.0])
            extra = Boxes(b.frame, b.centers[i:i + 1] + side, b.sizes[i:i + 1].copy(), b.yaws[i:i + 1].copy(),
                          b.velocities[i:i + 1].copy(), [old.category], [twin.token], [new_token(rng)])
            boxes[frames[f].token] = _replace_boxes(b, extra=extra)
        hit.duplicated[old.token] = (twin.token, window)
    for _ in range(options.false_positive_boxes):
        placed = _false_positive(log, options, rng)
        if placed is None:
            continue
        centre, yaw, fp_frames = placed
        ghost = TrackRecord(new_token(rng), "vehicle", FALSE_POSITIVE_SIZE[1], FALSE_POSITIVE_SIZE[0], FALSE_POSITIVE_SIZE[2])
        tracks.append(ghost)
        for f in fp_frames:
            b = boxes[frames[f].token]
            extra = Boxes(b.frame, (centre + world.origin)[None], np.array([FALSE_POSITIVE_SIZE]), np.array([yaw]),
                          np.zeros((1, 3)), ["vehicle"], [ghost.token], [new_token(rng)])
            boxes[frames[f].token] = _replace_boxes(b, extra=extra)
        hit.false_positives[ghost.token] = fp_frames
    return tracks, boxes, hit
