"""README.md runs as written: every command and Python snippet of it, extracted from the file itself, runs
against one shared build and gives what it promises.

Extraction (generic, so new README lines are picked up without touching this test):
- every line of a fenced ```bash block, its trailing `# comment` removed and split at ` ; `: each command
  starting with `nuplan-occ` or `occgen` is one case, run by bash in the workspace below (so
  `$NUPLAN_DATA_ROOT` expands from the environment); other commands (`make ...`) are not run, nor
  are lines holding ` ... ` (a sketch of options in the context of an earlier line);
- every ```python block is one case, exec'd in the workspace; afterwards every top-level name bound to
  a sized object (a dataset, clips, a list) must be non-empty: a snippet that gives nothing fails;
- a fenced block of any other language whose first line is `# <file>: ...` is written to the
  workspace as <file> before anything runs (e.g. `my.toml`).
Cases run in README order (later commands use what earlier ones wrote, e.g. occgen's ckpt/).

Placeholders, all real paths of the workspace (a temporary folder, the current directory of every case):
- `$NUPLAN_DATA_ROOT`: a synthetic nuPlan data root (`readme_root`: one 1.2 s scene, read only);
- `out/`: the dataset built by the README's first `nuplan-occ build ... out/` line, run once by the
  session fixture (its own case then checks that build);
- `truth/`: the synthetic data root's exact truth dataset;
- `RELEASE/`: the shared build's frames written in the released Nuplan-Occ's dense layout;
- `preds/`: a model's predictions of the shared build's frames, one `<token>.npy` each;
- any other relative path (frame.png, occ3d/, ckpt/, ...) is written by the command that names it.
Promises checked besides the exit code: files named by `--screenshot`, `--json`, `--preview` exist and
are not empty; `--out` and export destinations hold files; a build publishes ok frames.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path


REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
PROGRAMS = ("nuplan-occ", "occgen")
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
FILE_BLOCK = re.compile(r"^#\s*([\w.-]+):")
OUTPUT_FILE_OPTIONS = ("--screenshot", "--json", "--preview")


@dataclass(frozen=True)
class Case:
    """One runnable piece of the README: kind "command" (a shell line) or "python" (a block)."""

    kind: str
    text: str

    @property
    def id(self) -> str:
        lines = [line for line in self.text.strip().splitlines() if not line.startswith(("import ", "from "))]
        return f"{self.kind}: {(lines or [self.text])[0][:70]}"


def readme_blocks(text: str) -> list[tuple[str, str]]:
    """(language, body) of every fenced block, in order."""
    return [(m.group(1), m.group(2)) for m in FENCE.finditer(text)]


def readme_cases(text: str) -> list[Case]:
    """The commands and Python blocks of the README, in order (see module docstring)."""
    cases = []
    for language, body in readme_blocks(text):
        if language == "python":
            cases.append(Case("python", body))
        elif language == "bash":
            for line in body.splitlines():
                for command in re.sub(r"\s+#.*$", "", line).split(" ; "):
                    if command.strip().split(" ", 1)[0] in PROGRAMS and " ... " not in command:
                        cases.append(Case("command", command.strip()))
    return cases


def readme_files(text: str) -> dict[str, str]:
    """File name -> content of the blocks that declare a file on their first line."""
    files = {}
    for language, body in readme_blocks(text):
        match = FILE_BLOCK.match(body)
        if language not in ("bash", "python") and match:
            files[match.group(1)] = body
    return files


CASES = readme_cases(README.read_text())
NAMESPACES: dict[str, dict] = {}
"""Python block -> the names it bound (for the checks of what a block promises)."""


def is_shared_build(case: Case) -> bool:
    return case is next(c for c in CASES if c.kind == "command" and c.text.startswith("nuplan-occ build ")
                        and " out/" in c.text)


def run_command(command: str, workspace: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", command], cwd=workspace, env=env, capture_output=True, text=True,
                          timeout=3600)


def check_promises(command: str, workspace: Path) -> None:
    """The files a command says it writes exist and are not empty."""
    words = shlex.split(command)
    for option in OUTPUT_FILE_OPTIONS:
        if option in words:
            written = workspace / words[words.index(option) + 1]
            assert written.is_file() and written.stat().st_size > 0, f"{command}: no {written}"
    folders = [words[words.index("--out") + 1]] if "--out" in words else []
    if words[:2] == ["nuplan-occ", "export"]:
        folders.append(words[3])
    for folder in folders:
        files = [p for p in (workspace / folder).rglob("*") if p.is_file() and p.stat().st_size > 0]
        assert files, f"{command}: wrote nothing under {folder}"
    if words[:2] == ["nuplan-occ", "build"]:
        from nuplan_occ.dataset import open_dataset

        assert len(open_dataset(str(workspace / words[3]))) > 0, f"{command}: no ok frame"


def run_python(block: str, workspace: Path) -> dict:
    namespace: dict = {"__name__": "__readme__"}
    previous = Path.cwd()
    os.chdir(workspace)
    try:
        exec(compile(block, "README.md python block", "exec"), namespace)
    finally:
        os.chdir(previous)
    return namespace


if __name__ == "__main__":  # list the cases: python tests/docs/readme_cases.py
    print("\n".join(c.id for c in CASES))
