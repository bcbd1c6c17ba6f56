"""Fixtures of the end-to-end build tests (the synthetic data root `synthetic_root` is in tests/conftest.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

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
    run_build(synthetic_root, str(out), build_params())
    return out
