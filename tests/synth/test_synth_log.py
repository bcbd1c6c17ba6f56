"""A short synthesized log read back through the project's readers; determinism; preview."""

from __future__ import annotations

import hashlib
import re
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.storage.digest import content_digests
from nuplan_occ.io.maps import NuplanMap, find_map
from nuplan_occ.io.reader import NuplanLog, points_to_ego
from nuplan_occ.synth import render_preview, synthesize
from nuplan_occ.synth.lidar import T_EGO_FROM_LIDAR
from nuplan_occ.synth.logbuild import FRAME_US, log_start
from nuplan_occ.synth.presets import SynthOptions, get_preset
from nuplan_occ.synth.world import build_world

SECONDS = 0.5  # 10 frames, 5 scenes of 2 frames


def _content(path: Path) -> bytes:
    """File bytes; for the GPKG its SQL dump without the write-time `last_change` stamps that
    nuplan_occ.io.maps lets SQLite fill in (not ours to change)."""
    if path.suffix != ".gpkg":
        return path.read_bytes()
    with sqlite3.connect(path) as db:
        dump = "\n".join(db.iterdump())
    return re.sub(r"'\d{4}-\d\d-\d\dT[0-9:.]+Z'", "'T'", dump).encode()


def _digest(root: Path) -> dict[str, str]:
    """sha256 of every file of the data root, the truth dataset's published content taken as
    `content_digests` gives it (its manifest fragments are named by commit ids, new every run)."""
    truth = root / "truth"
    files = {str(p.relative_to(root)): hashlib.sha256(_content(p)).hexdigest()
             for p in sorted(root.rglob("*")) if p.is_file() and truth not in p.parents}
    return {**files, **{f"truth/{item}": digest for item, digest in content_digests(str(truth)).items()}}


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_a")
    messages = []
    result = synthesize(root, logs=1, seconds=SECONDS, seed=3, progress=messages.append, camera_mask=False)
    assert messages and result.truth_frames == 10
    return root, result


def test_same_seed_same_bytes(out, tmp_path):
    root, _ = out
    synthesize(tmp_path, logs=1, seconds=SECONDS, seed=3, camera_mask=False)
    assert _digest(root) == _digest(tmp_path)


def test_log_reads_back(out):
    root, result = out
    assert len(result.db_paths) == 1
    with NuplanLog(result.db_paths[0]) as log:
        assert log.meta.map_name == "us-nv-las-vegas-strip"
        assert len(log.frames) == 10 and len(log.scenes) >= 5
        names = [s.name for s in log.scenes]
        assert names == sorted(names) and names[0] == "scene-0000"
        assert np.allclose(log.lidar.T_ego_from_lidar, T_EGO_FROM_LIDAR, atol=1e-9)
        assert not np.allclose(log.lidar.T_ego_from_lidar, np.eye(4))
        assert len(log.cameras) == 8
        frame = log.frames[4]
        cloud = log.load_points(frame)
        assert cloud.frame == "lidar" and 30_000 < len(cloud) < 80_000
        assert set(np.unique(cloud.lidar_info).tolist()) == {0, 1, 2, 3, 4}
        # logged pose = TRUE pose + drift/noise: close, but not equal
        world = build_world(get_preset("small"), SynthOptions(), 3, 0, SECONDS, int(log_start(3, 0).timestamp()) * 1_000_000)
        T_true = world.true_pose(frame.timestamp_us)
        T_log = log.frame_pose(frame)
        gap = np.linalg.norm(T_log[:3, 3] - T_true[:3, 3])
        assert 1e-4 < gap < 1.0
        assert frame.timestamp_us == world.start_us + 4 * FRAME_US
        # points go to the ego frame with the stored extrinsic; on the ground they sit at z ~ -axle height
        ego = points_to_ego(cloud, log)
        near = np.linalg.norm(ego.xyz[:, :2], axis=1) < 15
        assert abs(np.median(ego.xyz[near, 2]) + SynthOptions().axle_height_m) < 0.2
        boxes = log.boxes(frame)
        boxed = {a.instance: a for a in world.agents if a.boxed}
        assert 0 < len(boxes) <= len(boxed)
        t = float(world.seconds(frame.timestamp_us))
        true_centers = np.array([a.state(np.array([t]))[0][0] for a in boxed.values()]) + world.origin
        nearest = np.min(np.linalg.norm(boxes.centers[:, None] - true_centers[None], axis=2), axis=1)
        assert np.all(nearest < 0.6)


def test_map_and_truth_read_back(out):
    root, _ = out
    gpkg = find_map(root / "maps", "us-nv-las-vegas-strip")
    nmap = NuplanMap(gpkg)
    lines = nmap.layer("boundaries")
    assert len(lines) > 10
    x, y = np.asarray(lines.geometries[0].coords).T
    assert 663000 < x.mean() < 665000 and 3996000 < y.mean() < 3998000
    ds = open_dataset(str(root / "truth"))
    assert len(ds) == 10
    item = ds.get(3)
    assert item["semantics"].shape == (400, 400, 32) and item["instance"].dtype == np.uint16
    assert item["mask_lidar"].any() and (item["semantics"] == 12).any()


def test_preview_renders(out, tmp_path):
    root, _ = out
    png = render_preview(root, tmp_path / "p.png", frame=2)
    assert png.stat().st_size > 10_000


def test_bad_arguments_raise(tmp_path):
    with pytest.raises(ValueError, match="preset"):
        synthesize(tmp_path, preset="huge")
    with pytest.raises(ValueError, match="truth_rate_hz"):
        synthesize(tmp_path, truth_rate_hz=7.0)
    with pytest.raises(ValueError, match="camera_rate_hz"):
        synthesize(tmp_path, camera_rate_hz=3.0)


def test_scene_seconds_lets_one_scene_span_the_log(tmp_path):
    result = synthesize(tmp_path, logs=1, seconds=SECONDS, seed=3, scene_seconds=SECONDS, truth_rate_hz=10.0,
                        camera_rate_hz=0.0, camera_mask=False)
    assert result.truth_frames == 5
    with NuplanLog(result.db_paths[0]) as log:
        assert len(log.scenes) == 1 and len(log.frames_of_scene(log.scenes[0].token)) == 10
    with pytest.raises(ValueError, match="scene_seconds"):
        synthesize(tmp_path / "bad", logs=1, seconds=SECONDS, scene_seconds=0.0)
