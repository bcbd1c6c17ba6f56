"""Suite-wide fixtures. The machines running the suite have 2 shared cores: torch runs on one thread in
every test (a test that measures threading sets its own count). `synthetic_root`: a small synthetic
nuPlan data root (1.2 s, 5 scenes, seed 7), made once per session and shared by every end-to-end test
(never modify it; copy it first)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch


@pytest.fixture(autouse=True)
def _torch_one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    from nuplan_occ.synth.generate import synthesize

    root = tmp_path_factory.mktemp("synth") / "data"
    synthesize(root, logs=1, seconds=1.2, seed=7, preset="small")
    return root
