"""Suite-wide fixtures. The machines running the suite have 2 shared cores: torch runs on one thread in
every test (a test that measures threading sets its own count)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _torch_one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
