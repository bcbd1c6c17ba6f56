"""Fixtures of the end-to-end build tests (the synthetic data root `synthetic_root` is in tests/conftest.py)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
from nuplan_occ.stages import PIPELINE

@pytest.fixture
def data_root(synthetic_root, tmp_path) -> Path:
    """A private copy that a test may damage."""
    copy = tmp_path / "data"
    shutil.copytree(synthetic_root, copy)
    return copy


@pytest.fixture(scope="session")
def reference_build(synthetic_root, tmp_path_factory) -> Path:
    """An uninterrupted local build (fast params) that other builds must reproduce byte for byte."""
    from nuplan_occ.pipeline.build import run_build
    from pipeline_helpers import build_params

    out = tmp_path_factory.mktemp("reference") / "out"
    run_build(synthetic_root, str(out), build_params(), pipeline=PIPELINE)
    return out


CORRUPT_PCD = (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 99\nHEIGHT 1\n"
               b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 99\nDATA binary\n\x00\x01")
"""A PCD whose header promises 99 points and whose data holds two bytes."""


@dataclass
class DamagedBuild:
    """A build (default params) of a copy of the synthetic root with one corrupt and one missing PCD."""

    data_root: Path
    out: Path
    summary: object
    corrupt: object
    missing: object


@pytest.fixture(scope="session")
def bad_blobs_build(synthetic_root, tmp_path_factory) -> DamagedBuild:
    from nuplan_occ.io.reader import NuplanLog
    from nuplan_occ.pipeline.build import run_build
    from pipeline_helpers import build_params

    base = tmp_path_factory.mktemp("damaged")
    data_root = base / "data"
    shutil.copytree(synthetic_root, data_root)
    db = next((data_root / "nuplan-v1.1" / "splits" / "mini").glob("*.db"))
    blobs = data_root / "nuplan-v1.1" / "sensor_blobs"
    with NuplanLog(db, blobs) as log:
        frames = list(log.frames)
    corrupt, missing = frames[2], frames[4]
    (blobs / corrupt.filename).write_bytes(CORRUPT_PCD)
    (blobs / missing.filename).unlink()
    out = base / "out"
    summary = run_build(data_root, str(out), build_params(fast=False), pipeline=PIPELINE)
    return DamagedBuild(data_root, out, summary, corrupt, missing)
