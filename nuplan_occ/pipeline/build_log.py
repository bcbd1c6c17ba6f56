"""The build log: one JSON line per build run and per finished scene, appended to `WORK/build_log.jsonl`.

It lives beside the stage cache, not in the published dataset, because times differ from run to run while
the dataset's files stay byte-identical across reruns. Lines:

- `{"kind": "run", "run": id, "started_utc": ISO time, "versions": {package: version}}` when a build starts;
- `{"kind": "scene", "run": id, "log", "scene", "scene_token", "frames": manifest rows of the scene,
  "stage_seconds": {stage: s} of the stages that ran in this run (stages answered by the cache are absent),
  "error": "" or why the scene failed, "peak_rss_mb": worker peak RSS}` per finished scene.

`scene_seconds` folds the runs together: each stage counts with its latest measured time, which is the
time that made the stage output the scene's current frames were written from (unless a param was set back
to an older value whose cached output is reused: then the latest time measured is that of the newer value).
"""

from __future__ import annotations

import json
import os
import time
from importlib import metadata
from pathlib import Path

LOG_NAME = "build_log.jsonl"
VERSIONED_PACKAGES = ("nuplan-occ", "numpy", "torch", "open3d-cpu", "open3d", "pyarrow", "scipy")


def package_versions() -> dict[str, str]:
    """Installed versions of the packages whose numbers shape a build (absent ones left out)."""
    versions = {}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


class BuildLog:
    """Appends the lines of one build run to `work_root/build_log.jsonl` (created on first use)."""

    def __init__(self, work_root: Path):
        self.path = Path(work_root) / LOG_NAME
        self.run = f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{os.getpid()}"
        self._append({"kind": "run", "run": self.run, "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                      "versions": package_versions()})

    def _append(self, entry: dict) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json.dumps(entry, sort_keys=True) + "\n")

    def scene(self, scene_token: str, result) -> None:
        """Record one finished scene (a `SceneResult` whose rows are final)."""
        self._append({"kind": "scene", "run": self.run, "log": result.log_name, "scene": result.scene_name,
                      "scene_token": scene_token, "frames": result.frames_built + result.frames_failed,
                      "stage_seconds": {k: round(v, 4) for k, v in result.stage_seconds.items()},
                      "error": result.error, "peak_rss_mb": round(result.peak_rss_mb, 1)})


def read_build_log(work_root: Path) -> list[dict]:
    """The lines of `work_root/build_log.jsonl` in order ([] when there is none; a torn last line is skipped)."""
    path = Path(work_root) / LOG_NAME
    if not path.exists():
        return []
    entries = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return entries


def scene_seconds(entries: list[dict]) -> dict[str, dict[str, float]]:
    """scene_token -> {stage: latest measured seconds} over every run of the log (see module docstring)."""
    seconds: dict[str, dict[str, float]] = {}
    for entry in entries:
        if entry.get("kind") == "scene":
            seconds.setdefault(entry["scene_token"], {}).update(entry.get("stage_seconds", {}))
    return seconds


def latest_versions(entries: list[dict]) -> dict[str, str]:
    """The package versions of the latest run ({} without a log)."""
    runs = [e for e in entries if e.get("kind") == "run"]
    return dict(runs[-1].get("versions", {})) if runs else {}
