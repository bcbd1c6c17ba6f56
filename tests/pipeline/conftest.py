"""A small synthetic nuPlan data root shared by the end-to-end build tests (made once per session)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from nuplan_occ.pipeline.params import apply_overrides, default_params

FAST_OVERRIDES = {"reconstruct": {"method": "poisson", "object_method": "poisson"}}
"""The cheaper surface method for tests that build many times (resume, executors); the default
method (the torch solver) is exercised by test_build_end_to_end."""


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    from nuplan_occ.synth.generate import synthesize

    root = tmp_path_factory.mktemp("synth") / "data"
    synthesize(root, logs=1, seconds=1.6, seed=7, preset="small")
    return root


@pytest.fixture
def data_root(synthetic_root, tmp_path) -> Path:
    """A private copy that a test may damage."""
    copy = tmp_path / "data"
    shutil.copytree(synthetic_root, copy)
    return copy


def build_params(fast: bool = True) -> dict:
    from stages import PIPELINE

    params = default_params(PIPELINE)
    return apply_overrides(params, FAST_OVERRIDES, "tests") if fast else params
