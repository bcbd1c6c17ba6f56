"""A small synthetic nuPlan data root shared by the end-to-end build tests (made once per session)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    from nuplan_occ.synth.generate import synthesize

    root = tmp_path_factory.mktemp("synth") / "data"
    synthesize(root, logs=1, seconds=1.2, seed=7, preset="small")
    return root


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
