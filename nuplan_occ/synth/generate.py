"""`synthesize`: procedural worlds written as nuPlan logs + map + exact truth in the dataset format.

Output under out_root:
  nuplan-v1.1/splits/mini/<logfile>.db, nuplan-v1.1/sensor_blobs/<logfile>/MergedPointCloud/*.pcd,
  nuplan-v1.1/sensor_blobs/<logfile>/<camera channel>/*.jpg (synth.cameras, synth.camera_render)
  maps/nuplan-maps-v1.0.json, maps/<location>/<version>/map.gpkg
  truth/ (DatasetWriter layout: dataset.json, manifest.parquet, shards/<logfile>/<scene>-<chunk>.tar)
Truth frames are in the ego frame of the TRUE pose (`FrameRecord.ego_to_global` = TRUE T_global_from_ego).
Everything is a pure function of (seed, preset, options, seconds, logs): same inputs, same bytes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nuplan_occ.io.maps import write_map_root
from nuplan_occ.io.types import ImageRecord, LidarFrame, PointCloud
from nuplan_occ.io.writer import sensor_blobs_root, write_blob, write_log
from nuplan_occ.storage import DatasetWriter, FrameRecord
from nuplan_occ.synth.camera_render import RigRays, colorize, encode_jpeg, render_labels, rig_rays
from nuplan_occ.synth.cameras import IMAGE_HEIGHT, IMAGE_WIDTH
from nuplan_occ.synth.lidar import sweep_at
from nuplan_occ.synth.logbuild import LogPlan, build_log, frame_count, log_start
from nuplan_occ.synth.mapgen import map_layers
from nuplan_occ.synth.presets import Preset, SynthOptions, get_preset
from nuplan_occ.synth.sensor_artefacts import with_artefacts
from nuplan_occ.synth.truth import truth_for_frame
from nuplan_occ.synth.world import LOCATIONS, World, build_static, build_world

SHARD_FRAMES = 10
"""Truth frames per tar shard (bounds memory: ~20 MB of raw arrays per frame)."""


@dataclass
class SynthResult:
    """What `synthesize` wrote: DB paths, map GPKG, truth root and counts."""

    out_root: Path
    db_paths: list[Path] = field(default_factory=list)
    map_path: Path | None = None
    truth_root: Path | None = None
    frames: int = 0
    truth_frames: int = 0
    images: int = 0
    points_per_sweep: float = 0.0


class _FramePass:
    """Point source for the log writer that also computes and shards the truth of the same sweep, so each
    sweep is ray cast once, and renders and writes the camera images taken at that frame. Called by
    `write_log` once per frame in time order."""

    def __init__(self, world: World, plan: LogPlan, writer: DatasetWriter, log_id: int, truth_every: int,
                 blobs: Path, camera_mask: bool):
        self.world, self.plan, self.writer = world, plan, writer
        self.log_id, self.truth_every, self.blobs, self.camera_mask = log_id, truth_every, blobs, camera_mask
        self.pending: list[FrameRecord] = []
        self.rows: list[dict] = []
        self.points = 0
        self.images = 0
        self.chunk = 0
        self.images_at: dict[int, list[ImageRecord]] = {}  # timestamp (us) -> the images taken then
        for image in plan.content.images:
            self.images_at.setdefault(image.timestamp_us, []).append(image)
        self.rays: RigRays | None = rig_rays(plan.content.cameras) if plan.content.images else None

    def write_images(self, frame: LidarFrame, T_true: np.ndarray) -> None:
        """Render and write the images taken at `frame` (same time and TRUE pose as its sweep)."""
        images = self.images_at.get(frame.timestamp_us, [])
        if not images:
            return
        by_camera = {image.camera_token: image for image in images}
        labels, depths = render_labels(self.world, frame.timestamp_us, T_true, self.rays)
        for camera, label, depth in zip(self.rays.cameras, labels, depths):
            if camera.token in by_camera:
                write_blob(self.blobs / by_camera[camera.token].filename_jpg, encode_jpeg(colorize(label, depth)))
                self.images += 1

    def __call__(self, frame: LidarFrame) -> PointCloud:
        T_true = self.plan.true_poses[frame.index]
        sweep = sweep_at(self.world, frame.timestamp_us, T_true)
        self.points += len(sweep.points)
        self.write_images(frame, T_true)
        if frame.index % self.truth_every == 0:
            arrays = truth_for_frame(self.world, frame.timestamp_us, T_true, sweep=sweep,
                                     cameras=self.plan.content.cameras if self.camera_mask else None)
            scene = self.plan.frame_scene[frame.index]
            if self.pending and self.pending[-1].scene_token != scene.token:
                self.flush()
            self.pending.append(FrameRecord(
                self.plan.content.meta.logfile, self.log_id, scene.token, scene.name, frame.index, frame.token,
                frame.timestamp_us, T_true, arrays, {"synthetic": True, "points": int(len(sweep.points))}))
            if len(self.pending) >= SHARD_FRAMES:
                self.flush()
        artefact_rng = np.random.default_rng([*self.world.noise_key, frame.timestamp_us, 0xA27E])
        return with_artefacts(sweep, self.world.options, -self.world.options.axle_height_m, artefact_rng).cloud()

    def flush(self) -> None:
        """Write the pending truth frames as one shard of their scene."""
        if not self.pending:
            return
        first = self.pending[0]
        key = f"{first.log}/{first.scene_name}-{self.chunk:03d}"
        self.rows += self.writer.write_shard(key, self.pending)
        self.pending, self.chunk = [], self.chunk + 1


def _params(preset: Preset, options: SynthOptions, logs: int, seconds: float, seed: int, truth_rate_hz: float,
            camera_rate_hz: float, camera_mask: bool) -> dict:
    return {"generator": "nuplan_occ.synth", "preset": preset.name, "logs": logs, "seconds": seconds, "seed": seed,
            "truth_rate_hz": truth_rate_hz, "camera_rate_hz": camera_rate_hz, "camera_mask": camera_mask,
            "image_size": [IMAGE_WIDTH, IMAGE_HEIGHT], "options": asdict(options),
            "truth_frame": "ego frame of the TRUE pose (rear axle above the ground by options.axle_height_m); ego_to_global is the TRUE pose",
            "truth_rules": "surfaces exact triangle/voxel overlap; box objects solid in their cuboid parts; priority objects > other > "
                           "road_line > road > other_ground; mask_lidar = voxels traversed by returned rays; mask_camera = voxels "
                           "up to and including the first occupied one along a ray through every pixel cell of the "
                           "8 cameras (pinhole K, distortion ignored, within 60 m)"}


def synthesize(out_root: Path, logs: int = 1, seconds: float = 10.0, seed: int = 0, preset: str = "small",
               options: SynthOptions | None = None, truth_rate_hz: float = 20.0,
               progress: Callable[[str], None] | None = None, location: str = "us-nv-las-vegas-strip",
               scene_seconds: float | None = None, camera_rate_hz: float = 10.0, camera_mask: bool = False) -> SynthResult:
    """Write `logs` synthetic logs of `seconds` each (20 Hz sweeps), their map and their truth under out_root.
    scene_seconds: scene length (None: the preset's, at least 5 scenes per log; see logbuild.build_log).

    truth_rate_hz must divide 20 (truth every 20 / rate frames). camera_rate_hz: images of the 8 cameras
    per second, 20 / n (at every n-th sweep, from the first; nuPlan's cameras run at 10 Hz) or 0 for no
    images (the camera rows are written either way). camera_mask: the truth frames get mask_camera (exact at
    the cameras' resolution, see synth.truth: the costliest part of the truth). progress(str) receives one
    line per step. Raises ValueError on a bad preset, rate or duration.
    """
    if logs < 1 or seconds <= 0 or (scene_seconds is not None and scene_seconds <= 0):
        raise ValueError(f"synthesize: need logs >= 1, seconds > 0 and scene_seconds > 0, got logs={logs}, seconds={seconds}, "
                         f"scene_seconds={scene_seconds}")
    every = 20.0 / truth_rate_hz if truth_rate_hz > 0 else 0.0
    if every < 1 or abs(every - round(every)) > 1e-9:
        raise ValueError(f"synthesize: truth_rate_hz must be 20 / n for an integer n >= 1, got {truth_rate_hz}")
    image_every = 20.0 / camera_rate_hz if camera_rate_hz > 0 else 0.0
    if camera_rate_hz < 0 or (camera_rate_hz > 0 and (image_every < 1 or abs(image_every - round(image_every)) > 1e-9)):
        raise ValueError(f"synthesize: camera_rate_hz must be 0 or 20 / n for an integer n >= 1, got {camera_rate_hz}")
    say = progress or (lambda _msg: None)
    spec = get_preset(preset)
    opts = options or SynthOptions()
    out_root = Path(out_root)
    result = SynthResult(out_root, truth_root=out_root / "truth")

    epsg, version, (east, north) = LOCATIONS[location]
    net, _, _ = build_static(spec, seed)
    result.map_path = write_map_root(out_root / "maps", location, version, epsg, map_layers(net, np.array([east, north])))
    say(f"map {location} {version} -> {result.map_path}")

    params = _params(spec, opts, logs, seconds, seed, truth_rate_hz, camera_rate_hz, camera_mask)
    writer = DatasetWriter(str(result.truth_root), {"params": params})
    for log_index in range(logs):
        start = log_start(seed, log_index)
        start_us = int(start.timestamp()) * 1_000_000
        world = build_world(spec, opts, seed, log_index, seconds, start_us, location)
        plan = build_log(world, seconds, seed, log_index, start, scene_seconds, int(round(image_every)))
        frame_pass = _FramePass(world, plan, writer, log_index, int(round(every)), sensor_blobs_root(out_root),
                                camera_mask)
        say(f"log {log_index + 1}/{logs} {plan.content.meta.logfile}: {frame_count(seconds)} frames, "
            f"{len(world.agents)} agents, ego turns {world.ego.turns[:3]}")
        result.db_paths.append(write_log(plan.content, out_root, split="mini", point_source=frame_pass))
        frame_pass.flush()
        writer.commit(frame_pass.rows)
        result.frames += len(plan.content.frames)
        result.truth_frames += len(frame_pass.rows)
        result.images += frame_pass.images
        result.points_per_sweep += frame_pass.points
        say(f"log {log_index + 1}/{logs} written: {len(frame_pass.rows)} truth frames, {frame_pass.images} images")
    result.points_per_sweep /= max(result.frames, 1)
    return result
