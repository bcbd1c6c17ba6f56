"""The README workspace: a folder laid out as README.md assumes, with its shared build (see readme_cases)."""

from __future__ import annotations

import os

import pytest

from readme_cases import CASES, README, REPO, is_shared_build, readme_files, run_command


@pytest.fixture(scope="session")
def workspace(synthetic_root, tmp_path_factory):
    """(folder, environment) laid out as the README assumes; the shared build is made here."""
    folder = tmp_path_factory.mktemp("readme")
    for name, content in readme_files(README.read_text()).items():
        (folder / name).write_text(content)
    (folder / "truth").symlink_to(synthetic_root / "truth")
    env = {**os.environ, "NUPLAN_DATA_ROOT": str(synthetic_root), "COLUMNS": "100",
           "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    build = next(c for c in CASES if is_shared_build(c))
    result = run_command(build.text, folder, env)
    assert result.returncode == 0, f"{build.text}\n{result.stderr[-3000:]}"
    return folder, env
