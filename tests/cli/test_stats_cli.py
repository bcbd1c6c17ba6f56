"""dataset_stats() from the manifest, and the dataset CLI commands (view, eval, stats, validate, export)."""

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from nuplan_occ.cli.dataset import register
from nuplan_occ.labels import LABELS
from nuplan_occ.stats import dataset_stats
from nuplan_occ.storage import read_manifest
from tools_world import SMALL, small_scene, write_dataset

COLUMNS = {
    0: {"qa_points": 1000, "qa_pose_accepted": True, "qa_map_status": "ok", "qa_point_coverage": 0.9},
    1: {"qa_points": 3000, "qa_pose_accepted": False, "qa_map_status": "ok", "qa_point_coverage": float("nan")},
    2: {"qa_points": 2000, "qa_pose_accepted": True, "qa_map_status": "no_map", "qa_point_coverage": 0.5},
}


@pytest.fixture(scope="module")
def small_ds(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    frames = [{"semantics": small_scene(i), "mask_lidar": np.ones(SMALL.shape, dtype=bool)} for i in range(3)]
    write_dataset(root, frames, failed={3: "registration failed", 4: "registration failed", 5: "no lidar"},
                  columns=COLUMNS)
    return str(root), frames


def test_stats_from_the_manifest(small_ds):
    root, frames = small_ds
    stats = dataset_stats(root)
    assert stats["frames"] == {"total": 6, "ok": 3, "failed": 3, "logs": 1, "scenes": 1}
    assert stats["failure_reasons"] == {"registration failed": 2, "no lidar": 1}
    counts = sum(np.bincount(f["semantics"].reshape(-1), minlength=256) for f in frames)
    assert {c["id"]: c["voxels"] for c in stats["classes"]} == {i: int(counts[i]) for i in np.flatnonzero(counts)}
    assert {c["name"] for c in stats["classes"]} == {LABELS.names[i] for i in np.flatnonzero(counts)}
    occupied = [c["fraction_of_occupied"] for c in stats["classes"] if c["id"]]
    assert sum(occupied) == pytest.approx(1.0)
    manifest = read_manifest(root)
    sem = [v for v in manifest["semantics_nbytes"].to_pylist() if v is not None]
    assert stats["bytes"]["semantics"] == {"frames": 3, "mean": np.mean(sem), "median": np.median(sem),
                                           "max": max(sem), "total": sum(sem)}
    assert set(stats["bytes"]) == {"semantics", "mask_lidar"}
    qa = stats["qa"]
    assert qa["qa_points"] == {"n": 3, "null": 0, "median": 2000.0, "min": 1000.0, "max": 3000.0}
    assert qa["qa_point_coverage"]["n"] == 2 and qa["qa_point_coverage"]["null"] == 1
    assert qa["qa_point_coverage"]["median"] == pytest.approx(0.7)
    assert qa["qa_pose_accepted"]["fraction_true"] == pytest.approx(2 / 3)
    assert qa["qa_map_status"]["counts"] == {"ok": 2, "no_map": 1}


@pytest.fixture(scope="module")
def cli():
    app = typer.Typer()
    register(app)
    return lambda *args: CliRunner().invoke(app, [str(a) for a in args])


def test_cli_stats_eval_export(small_ds, cli, tmp_path):
    root, _ = small_ds
    out = cli("stats", root)
    assert out.exit_code == 0, out.output
    assert "registration failed" in out.output and "qa_points" in out.output and "road" in out.output
    out = cli("eval", root, root, "--json", tmp_path / "e.json")
    assert out.exit_code == 0, out.output
    assert "occupied" in out.output and "1.0000" in out.output and (tmp_path / "e.json").is_file()
    out = cli("export", root, tmp_path / "exp", "--format", "uniscene")
    assert out.exit_code == 0, out.output
    assert len(list((tmp_path / "exp").glob("nuplan_quantized_32_32_8/*.npy"))) == 3


def test_cli_validate_exit_codes(tmp_path, cli):
    write_dataset(tmp_path / "ds", [{"semantics": small_scene(0)}])
    assert cli("validate", tmp_path / "ds").exit_code == 0
    shard = next((tmp_path / "ds" / "shards").rglob("*.tar"))
    data = bytearray(shard.read_bytes())
    data[1024] ^= 0xFF  # inside the first member's data
    shard.write_bytes(bytes(data))
    out = cli("validate", tmp_path / "ds")
    assert out.exit_code == 1 and "problem" in out.output


def test_cli_view_screenshot_skips_unreachable_points(small_ds, cli, tmp_path):
    root, _ = small_ds
    png = tmp_path / "v.png"
    out = cli("view", root, "--index", 1, "--mask", "lidar", "--points", "--data-root", tmp_path / "nowhere",
              "--screenshot", png)
    assert out.exit_code == 0, out.output
    assert "--points skipped" in out.output and png.stat().st_size > 1000
