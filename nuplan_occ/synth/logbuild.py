"""The nuPlan DB content (`LogContent`) of a synthetic log: logged (imperfect) ego poses, scenes, 20 Hz
frames, tracks and noisy boxes, the MergedPointCloud calibration, 8 cameras and their image rows. Frames: ego poses and
boxes in "global" (UTM); camera and lidar extrinsics sensor -> ego."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

import numpy as np

from nuplan_occ.io.types import (
    LIDAR_CHANNEL, Boxes, EgoPoseRecord, LidarCalibration, LidarFrame, LogContent, LogMeta, SceneRecord, TrackRecord,
)
from nuplan_occ.io.writer import new_token
from nuplan_occ.synth.auto_label import LabelFailures, apply_label_failures
from nuplan_occ.synth.cameras import camera_rig, image_records
from nuplan_occ.synth.imperfect import logged_poses, noisy_boxes, pose_errors, track_size_bias
from nuplan_occ.synth.lidar import T_EGO_FROM_LIDAR
from nuplan_occ.synth.world import World

FRAME_US = 50_000
"""lidar_pc period (20 Hz)."""

_BASE_TIME = datetime(2021, 5, 12, 22, 0, 38, tzinfo=timezone.utc)


def log_start(seed: int, log_index: int) -> datetime:
    """Start time (UTC) of log `log_index` of a seed: one log per hour after the base time."""
    return _BASE_TIME + timedelta(hours=log_index, minutes=seed % 60)


def logfile_name(start: datetime, log_index: int, n_frames: int) -> str:
    """nuPlan-style log name, e.g. 2021.05.12.22.00.38_veh-35_00001_00201."""
    first = 1 + log_index * 1000
    return f"{start:%Y.%m.%d.%H.%M.%S}_veh-35_{first:05d}_{first + n_frames:05d}"


def frame_count(seconds: float) -> int:
    """Number of 20 Hz frames of a log of `seconds`."""
    return max(1, int(round(seconds * 1e6 / FRAME_US)))


def scene_count(seconds: float, scene_seconds: float, min_scenes: int = 5) -> int:
    """Scenes per log: about seconds / scene_seconds, at least min_scenes (the devkit's scene enumeration
    wants 5; a real-scale log may be one scene spanning the whole log)."""
    return max(min_scenes, int(round(seconds / scene_seconds)))


@dataclass
class LogPlan:
    """A log's content plus what the truth pass needs: TRUE T_global_from_ego (F, 4, 4) per frame, and
    the scene of each frame."""

    content: LogContent
    true_poses: np.ndarray
    frame_scene: list[SceneRecord]
    label_failures: LabelFailures | None = None
    """Which tracks the auto-label failures of the world's options hit (synth.auto_label)."""


def build_log(world: World, seconds: float, seed: int, log_index: int, start: datetime,
              scene_seconds: float | None = None, image_every: int = 0) -> LogPlan:
    """LogContent of `world` over `seconds` (frames at 20 Hz from world.start_us). scene_seconds: length of
    a scene (None: the preset's, with at least 5 scenes per log; given: exactly about seconds / scene_seconds
    scenes, at least one). image_every: `image` rows for the 8 cameras at every image_every-th frame
    (`cameras.image_records`; 0: none; their tokens come from a stream of their own, so the rest of the
    content is the same with or without them)."""
    rng = np.random.default_rng([seed, log_index, 0x70CE])
    opts = world.options
    n_frames = frame_count(seconds)
    logfile = logfile_name(start, log_index, n_frames)
    meta = LogMeta(new_token(rng), logfile, "veh-35", f"{start:%Y-%m-%d}", world.start_us, world.location, world.location)
    lidar = LidarCalibration(new_token(rng), LIDAR_CHANNEL, "synthetic-5-lidar-merged", T_EGO_FROM_LIDAR.copy())
    cams = camera_rig(rng)

    ego_step = int(round(1e6 / opts.ego_pose_hz))
    ego_us = np.arange(0, (n_frames - 1) * FRAME_US + 1, ego_step, dtype=np.int64)
    state = world.ego_state(ego_us / 1e6)
    T_true = np.einsum("ij,tjk->tik", world.T_global_from_local, state["T_local_from_ego"])
    T_log = logged_poses(T_true, pose_errors(ego_us / 1e6, opts, rng))
    ego_tokens = [new_token(rng) for _ in ego_us]
    ego_poses = [EgoPoseRecord(tok, int(world.start_us + t), T_log[k], state["velocity"][k], state["acceleration"][k],
                               state["angular_rate"][k], world.epsg) for k, (tok, t) in enumerate(zip(ego_tokens, ego_us))]

    n_scenes = (scene_count(seconds, world.preset.scene_seconds) if scene_seconds is None
                else scene_count(seconds, scene_seconds, min_scenes=1))
    bounds = np.linspace(0, n_frames, n_scenes + 1).round().astype(int)
    scenes = []
    frame_scene = []
    for k in range(n_scenes):
        last = max(bounds[k], bounds[k + 1] - 1)
        goal = int(np.argmin(np.abs(ego_us - last * FRAME_US)))
        scenes.append(SceneRecord(new_token(rng), f"scene-{k:04d}", ego_tokens[goal]))
        frame_scene += [scenes[-1]] * (bounds[k + 1] - bounds[k])

    frame_tokens = [new_token(rng) for _ in range(n_frames)]
    frames = []
    for i, tok in enumerate(frame_tokens):
        t_rel = i * FRAME_US
        pose_index = int(np.argmin(np.abs(ego_us - t_rel)))
        frames.append(LidarFrame(tok, int(world.start_us + t_rel), f"{logfile}/{LIDAR_CHANNEL}/{tok}.pcd",
                                 frame_scene[i].token, ego_tokens[pose_index], lidar.token,
                                 frame_tokens[i - 1] if i else None, frame_tokens[i + 1] if i + 1 < n_frames else None, i))

    boxed = [a for a in world.agents if a.boxed]
    tracks = [TrackRecord(new_token(rng), a.category, 0.0, 0.0, 0.0) for a in boxed]
    bias = track_size_bias(len(boxed), opts, rng)
    for track, a, b in zip(tracks, boxed, bias):
        track.length, track.width, track.height = (float(v) for v in a.size * (1.0 + b))
    frame_t = np.arange(n_frames) * FRAME_US / 1e6
    true_frame_poses = np.einsum("ij,tjk->tik", world.T_global_from_local, world.ego_state(frame_t)["T_local_from_ego"])
    states = [a.state(frame_t) for a in boxed]
    boxes = {}
    for i, frame in enumerate(frames):
        ego_xy = true_frame_poses[i, :2, 3]
        centers = np.array([s[0][i] for s in states]).reshape(-1, 3) + world.origin
        near = np.flatnonzero(np.linalg.norm(centers[:, :2] - ego_xy, axis=1) <= opts.box_range_m)
        sizes = np.array([boxed[k].size for k in near]).reshape(-1, 3)
        c, sz, y = noisy_boxes(centers[near], sizes, np.array([states[k][1][i] for k in near]), bias[near], opts, rng)
        boxes[frame.token] = Boxes("global", c, sz, y, np.array([states[k][2][i] for k in near]).reshape(-1, 3),
                                   [boxed[k].category for k in near], [tracks[k].token for k in near],
                                   [new_token(rng) for _ in near])
    tracks, boxes, failures = apply_label_failures(world, boxed, tracks, boxes, frames, true_frame_poses, opts,
                                                   np.random.default_rng([seed, log_index, 0xBAD1]))
    images = (image_records(frames, cams, logfile, image_every, np.random.default_rng([seed, log_index, 0xCA3E]))
              if image_every else [])
    content = LogContent(meta, lidar, cams, ego_poses, scenes, frames, tracks, boxes, images)
    return LogPlan(content, true_frame_poses, frame_scene, failures)
