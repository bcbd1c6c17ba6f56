"""Expected failures end the real CLI with one line on stderr naming the file and the problem, and a
non-zero exit; `--debug` shows the traceback. `nuplan-occ stats` keeps full QA column names at 80 columns."""

from __future__ import annotations

import os
import pickle
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tools_world import SMALL, small_scene, write_dataset

REPO = Path(__file__).resolve().parents[2]
PROGRAMS = {"nuplan-occ": "nuplan_occ.cli", "occgen": "occgen.cli"}


def run_cli(program: str, *args, columns: int = 120) -> subprocess.CompletedProcess:
    """`program args` as a user runs it (python -m of the entry module, this checkout first on the path)."""
    env = {**os.environ, "COLUMNS": str(columns), "PYTHONPATH": os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    return subprocess.run([sys.executable, "-m", PROGRAMS[program], *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=300)


def assert_one_line(result: subprocess.CompletedProcess, program: str, *needles: str) -> str:
    assert result.returncode != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"{program}: error: ") and "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0]
    return lines[0]


class _Payload:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture
def poisoned_root(synthetic_root, tmp_path) -> tuple[Path, Path, Path]:
    """A data root whose log DB holds an os.system pickle as the LiDAR calibration; (root, db, marker)."""
    shutil.copytree(synthetic_root, tmp_path / "data")
    copy = next((tmp_path / "data").rglob("*.db"))
    marker = tmp_path / "pwned"
    connection = sqlite3.connect(copy)
    with connection:
        connection.execute("UPDATE lidar SET translation = ?", (pickle.dumps(_Payload(marker)),))
    connection.close()
    return tmp_path / "data", copy, marker


def test_refused_pickle_is_one_line_and_debug_shows_the_traceback(poisoned_root):
    root, db, marker = poisoned_root
    out = root.parent / "out"
    line = assert_one_line(run_cli("nuplan-occ", "build", root, out), "nuplan-occ", str(db), "lidar.translation")
    assert "refused" in line
    debug = run_cli("nuplan-occ", "--debug", "build", root, out)
    assert debug.returncode != 0 and "Traceback" in debug.stderr and "UnsafePickleError" in debug.stderr
    assert not marker.exists()


def test_missing_dataset_and_bad_config_are_one_line(synthetic_root, tmp_path):
    absent = tmp_path / "absent"
    assert_one_line(run_cli("nuplan-occ", "stats", absent), "nuplan-occ", str(absent), "dataset.json")
    assert_one_line(run_cli("occgen", "train", "vae", "--data", absent, "--out", tmp_path / "ckpt"), "occgen",
                    str(absent))
    assert_one_line(run_cli("nuplan-occ", "build", absent, tmp_path / "out"), "nuplan-occ", str(absent))
    config = tmp_path / "my.toml"
    config.write_text("[reconstruct]\nno_such_param = 1\n")
    assert_one_line(run_cli("nuplan-occ", "build", synthetic_root, tmp_path / "out", "--config", config),
                    "nuplan-occ", str(config), "no_such_param")
    assert not (tmp_path / "out").exists()


LONG_QA = {"qa_free_space_cleared": 2946, "qa_lidar_observed_fraction": 0.2367, "qa_pose_correction_deg": 0.08,
           "qa_boxes_with_points_unlabeled": 3, "qa_map_aligned": True, "qa_map_status": "no_paint"}


def test_stats_shows_full_qa_column_names_in_80_columns(tmp_path):
    frames = [{"semantics": small_scene(i), "mask_lidar": np.ones(SMALL.shape, dtype=bool)} for i in range(2)]
    write_dataset(tmp_path / "ds", frames, columns={i: LONG_QA for i in range(2)})
    result = run_cli("nuplan-occ", "stats", tmp_path / "ds", columns=80)
    assert result.returncode == 0, result.stderr
    assert max(len(line) for line in result.stdout.splitlines()) <= 80
    rows = {line.split()[1]: line for line in result.stdout.splitlines() if line.split()[1:2] and
            line.split()[1].startswith("qa_")}
    assert set(rows) == set(LONG_QA)
    assert "2,946" in rows["qa_free_space_cleared"] and "100.0% true" in rows["qa_map_aligned"]
    assert "no_paint: 2" in rows["qa_map_status"]
