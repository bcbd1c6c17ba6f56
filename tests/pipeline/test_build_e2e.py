"""End-to-end builds of a synthetic log: output contract, failures isolated to their frames, rerun does
no work, Ray and an fsspec URL match the local build (resume after SIGKILL: test_concurrent_builds)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.labels import LABELS
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.storage import read_manifest
from nuplan_occ.storage.digest import content_digests
from nuplan_occ.storage.validate import validate_dataset
from nuplan_occ.torch import OccupancyDataset
from nuplan_occ.stages import PIPELINE

from pipeline_helpers import build_params

pytestmark = pytest.mark.slow


def tree_digest(root: Path) -> dict[str, str]:
    """sha256 of every published item (shards, visible manifest rows without commit ids, metadata)."""
    return content_digests(str(root))


def sweep_files(data_root: Path) -> tuple[Path, list]:
    db = next((data_root / "nuplan-v1.1" / "splits" / "mini").glob("*.db"))
    with NuplanLog(db, data_root / "nuplan-v1.1" / "sensor_blobs") as log:
        return db, list(log.frames)


def test_build_end_to_end_default_method_with_bad_blobs(bad_blobs_build):
    data_root, out, summary = bad_blobs_build.data_root, bad_blobs_build.out, bad_blobs_build.summary
    corrupt, missing = bad_blobs_build.corrupt, bad_blobs_build.missing
    db, frames = sweep_files(data_root)

    manifest = read_manifest(str(out)).to_pylist()
    assert [r["token"] for r in manifest] == [f.token for f in frames if f.index % 2 == 0]
    failed = {r["token"]: r["failure_reason"] for r in manifest if r["status"] != "ok"}
    assert set(failed) == {corrupt.token, missing.token}
    assert corrupt.filename.split("/")[-1] in failed[corrupt.token]
    assert missing.filename.split("/")[-1] in failed[missing.token]
    assert summary.frames_failed == 2 and summary.frames_built == len(manifest) - 2
    assert validate_dataset(str(out)) == []
    # output frames are numbered 0, 1, 2, ... per scene; clips of 2 are the ok pairs, none across a failed frame
    by_scene: dict[str, list[dict]] = {}
    for r in manifest:
        by_scene.setdefault(r["scene_token"], []).append(r)
    assert all([r["output_index"] for r in rows] == list(range(len(rows))) for rows in by_scene.values())
    pairs = sum(a["status"] == b["status"] == "ok" for rows in by_scene.values() for a, b in zip(rows, rows[1:]))
    clips = OccupancyDataset(str(out), clip_len=2)
    assert len(clips) == pairs > 0
    assert all(np.diff(clips[i]["timestamp_us"].numpy()).tolist() == [100_000] for i in range(len(clips)))

    truth = {r["token"]: np.reshape(r["ego_to_global"], (4, 4)) for r in read_manifest(str(data_root / "truth")).to_pylist()}
    ok = [r for r in manifest if r["status"] == "ok"]
    assert all(r["qa_map_aligned"] for r in ok)
    # the written pose is the map-aligned one: it sits on the true pose where the logged one is centimetres off
    error = [np.linalg.norm(np.reshape(r["ego_to_global"], (4, 4))[:2, 3] - truth[r["token"]][:2, 3]) for r in ok]
    with NuplanLog(db, data_root / "nuplan-v1.1" / "sensor_blobs") as log:
        logged = [np.linalg.norm(log.frame_pose(f)[:2, 3] - truth[f.token][:2, 3]) for f in frames if f.token in truth]
    assert np.median(error) < 0.015 and np.median(error) < np.median(logged) / 2

    ds = open_dataset(str(out))
    frame = ds[0]
    assert frame["semantics"].shape == (400, 400, 32) and frame["semantics"].dtype == np.uint8
    assert {"mask_lidar", "mask_camera", "instance", "flow"} <= set(frame)
    assert (frame["semantics"] > 0).sum() > 10_000
    boxed = sorted(LABELS.box_category_to_id.values())
    for index in range(len(ds)):  # instance ids and flow only where an object voxel is, after free-space clearing
        grids = ds.get(index, keys=("semantics", "instance", "flow"))
        on_object = np.isin(grids["semantics"], boxed)
        assert not np.any(grids["instance"][~on_object]) and not np.any(grids["flow"][~on_object])

    before = tree_digest(out)
    again = run_build(data_root, str(out), build_params(fast=False), pipeline=PIPELINE)
    assert again.scenes_fully_cached == again.scenes
    assert tree_digest(out) == before


def test_ray_executor_matches_local(synthetic_root, reference_build, tmp_path):
    distributed = tmp_path / "ray"
    run_build(synthetic_root, str(distributed), build_params(), pipeline=PIPELINE, executor="ray", workers=2)
    assert tree_digest(distributed) == tree_digest(reference_build)


def test_build_to_an_fsspec_url_matches_the_local_build(synthetic_root, reference_build):
    import fsspec

    url = "memory://nuplan-occ-test/out"
    summary = run_build(synthetic_root, url, build_params(), pipeline=PIPELINE, work_root=reference_build / "work")
    # the default work policy dropped the grids and point clouds; the kept poses, boxes and surfaces are reused
    assert {p.name for p in (reference_build / "work").glob("*/*/*")} == {"register", "track", "reconstruct", "write"}
    assert "voxelize" in summary.stage_seconds and not {"register", "track", "reconstruct"} & set(summary.stage_seconds)
    assert content_digests(url) == tree_digest(reference_build)
    assert any("/manifest/shards/" in path for path in fsspec.filesystem("memory").find("/nuplan-occ-test/out"))
    assert len(open_dataset(url)) == len(open_dataset(str(reference_build)))
