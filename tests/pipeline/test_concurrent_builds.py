"""Many writers, one dataset: concurrent build processes (one, on 2 workers, SIGKILLed mid-scene and
rerun: resume after SIGKILL) end with the bytes of a serial build; build shards partition logs; the
work-folder policies."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nuplan_occ.pipeline.build import logs_of_shard
from nuplan_occ.stages import PIPELINE
from nuplan_occ.pipeline.publish import kept_stages, trim_work
from nuplan_occ.storage import read_manifest
from nuplan_occ.storage.digest import content_digests
from nuplan_occ.storage.validate import validate_dataset

from pipeline_helpers import FAST_CLI


@pytest.mark.slow
def test_three_concurrent_builds_one_killed_and_rerun_equal_a_serial_build(synthetic_root, reference_build, tmp_path):
    out = tmp_path / "shared"
    command = [sys.executable, "-m", "nuplan_occ.cli", "build", str(synthetic_root), str(out), *FAST_CLI]

    def start(*extra: str) -> subprocess.Popen:
        return subprocess.Popen([*command, *extra], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)

    killed = start("--workers", "2")
    others = [start(), start("--num-shards", "1", "--shard-index", "0")]  # the same log, at the same time
    deadline = time.monotonic() + 900
    # killed mid-scene: a scene's scene steps are cached and its frames stream
    while time.monotonic() < deadline and not list((out / "work").rglob("support/*.pkl.zst")):
        time.sleep(0.05)
    os.killpg(killed.pid, signal.SIGKILL)
    assert killed.wait() == -signal.SIGKILL
    assert [p.wait() for p in others] == [0, 0]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    assert content_digests(str(out)) == content_digests(str(reference_build))
    table = read_manifest(str(out))
    assert table.num_rows == read_manifest(str(reference_build)).num_rows  # one set of rows, none lost
    assert validate_dataset(str(out)) == []


def test_build_shards_partition_logs_by_name():
    logs = [Path(f"/data/splits/mini/2021.05.{i:02d}.12.00.00_veh-35_0{i}.db") for i in range(40)]
    shards = [logs_of_shard(logs, 3, i) for i in range(3)]
    assert sorted(p for shard in shards for p in shard) == sorted(logs)
    assert all(shard for shard in shards)
    assert logs_of_shard(list(reversed(logs)), 3, 1) == list(reversed(shards[1]))  # names alone decide
    with pytest.raises(ValueError, match="shard-index"):
        logs_of_shard(logs, 3, 3)


def test_work_policies(tmp_path):
    stages = [stage.name for stage in PIPELINE]
    kept = kept_stages(PIPELINE)
    assert kept == {"register", "track", "reconstruct", "write"}
    for policy in ("all", "default", "none"):
        scene = tmp_path / policy / "log" / "scene-0000"
        for stage in stages:
            (scene / stage).mkdir(parents=True)
            (scene / stage / "k.pkl.zst").write_bytes(b"x")
        trim_work(scene, policy, kept)
        left = sorted(p.name for p in scene.iterdir()) if scene.exists() else []
        assert left == {"all": sorted(stages), "default": sorted(kept), "none": []}[policy]
    with pytest.raises(ValueError, match="keep_work"):
        trim_work(tmp_path, "some", kept)
