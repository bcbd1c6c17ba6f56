"""README.md runs as written (the extraction and placeholder conventions are in readme_cases.py): every
`nuplan-occ` / `occgen` command and every Python block, in README order, against the shared build."""

from __future__ import annotations

from collections.abc import Sized

import pytest

from readme_cases import (CASES, NAMESPACES, README, check_promises, is_shared_build, readme_files, run_command,
                          run_python)


def test_readme_has_the_documented_cases():
    commands = [c.text for c in CASES if c.kind == "command"]
    for needed in ("nuplan-occ build", "nuplan-occ view", "nuplan-occ eval", "nuplan-occ stats",
                   "nuplan-occ validate", "--format occ3d", "--format uniscene", "--format mesh", "nuplan-occ synth",
                   "nuplan-occ summary", "nuplan-occ --debug", "occgen train vae", "--task spatial", "--task temporal",
                   "occgen render-maps", "occgen lidar"):
        assert any(needed in c for c in commands), needed
    assert any(c.kind == "python" and "DataLoader" in c.text for c in CASES)
    assert "my.toml" in readme_files(README.read_text())


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_readme_case(case: Case, workspace):
    folder, env = workspace
    if case.kind == "python":
        namespace = NAMESPACES[case.text] = run_python(case.text, folder)
        empty = [name for name, value in namespace.items()
                 if not name.startswith("_") and isinstance(value, Sized) and not isinstance(value, (str, type))
                 and len(value) == 0]
        assert not empty, f"README python block gives nothing for {empty}"
        return
    if not is_shared_build(case):
        result = run_command(case.text, folder, env)
        assert result.returncode == 0, f"{case.text}\n{result.stdout[-1500:]}\n{result.stderr[-3000:]}"
    check_promises(case.text, folder)


def test_python_blocks_promise_clips_of_the_documented_shape(workspace):
    """The DataLoader line's comment promises [B, T, 400, 400, 32]: B = batch_size, T = clip_len."""
    block = next(c.text for c in CASES if c.kind == "python" and "DataLoader" in c.text)
    namespace = NAMESPACES.get(block) or run_python(block, workspace[0])
    clips, batch = namespace["clips"], namespace["batch"]
    assert tuple(batch["semantics"].shape) == (min(2, len(clips)), clips.clip_len, 400, 400, 32)
    assert tuple(batch["flow"].shape[-1:]) == (3,)
