"""A small synthetic nuPlan data root shared by the end-to-end build tests (made once per session)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

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
