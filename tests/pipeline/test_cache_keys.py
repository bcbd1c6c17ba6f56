"""Cache keys derived from the code and the inputs: an edit of a module invalidates exactly the stages whose
import closure holds it and every stage after them; a restored input file rebuilds its scene."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import nuplan_occ
from nuplan_occ.pipeline.build import default_work_root, plan_tasks
from nuplan_occ.pipeline.code_key import import_closure
from nuplan_occ.pipeline.params import default_params
from nuplan_occ.pipeline.runner import stage_keys
from nuplan_occ.io.data_root import maps_root_for, resolve_logs
from nuplan_occ.stages import PIPELINE

_KEYS = """
import json, sys
from pathlib import Path
from nuplan_occ.io.data_root import maps_root_for, resolve_logs
from nuplan_occ.pipeline.build import plan_tasks
from nuplan_occ.pipeline.params import default_params
from nuplan_occ.pipeline.runner import stage_keys
from nuplan_occ.stages import PIPELINE
root = Path(sys.argv[1])
task = plan_tasks(resolve_logs(root, split=None), root, maps_root_for(root, None), sys.argv[2], Path(sys.argv[2]) / "work",
                  default_params(PIPELINE))[0]
print(json.dumps(stage_keys(task, PIPELINE)))
"""


def _keys_with_source(package: Path, data_root: Path, out: Path) -> dict[str, str]:
    """Stage keys of the first scene, computed by the nuplan_occ package at `package` in a fresh process."""
    done = subprocess.run([sys.executable, "-c", _KEYS, str(data_root), str(out)], check=True, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(package.parent)}, cwd=package.parent)
    return json.loads(done.stdout)


def _downstream_of(name: str) -> list[str]:
    """`name` and every stage that reads, directly or through other stages, what it makes (pipeline order)."""
    reached, made = [name], set(next(stage for stage in PIPELINE if stage.name == name).outputs)
    for stage in PIPELINE[[s.name for s in PIPELINE].index(name) + 1:]:
        if made & set(stage.inputs):
            reached.append(stage.name)
            made |= set(stage.outputs)
    return reached


def test_editing_a_module_only_track_imports_reruns_track_and_what_follows(synthetic_root, tmp_path):
    track_only = "nuplan_occ.tracks.track_icp"
    importers = [stage.name for stage in PIPELINE if track_only in import_closure(stage.run.__module__)]
    assert importers == ["track"]  # the premise: only the track stage's code reaches it
    copy = tmp_path / "src" / "nuplan_occ"
    shutil.copytree(Path(nuplan_occ.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = _keys_with_source(copy, synthetic_root, tmp_path / "out")
    edited = copy / "tracks" / "track_icp.py"
    edited.write_text(edited.read_text() + "\n# an edit\n")
    after = _keys_with_source(copy, synthetic_root, tmp_path / "out")
    changed = [stage.name for stage in PIPELINE if before[stage.name] != after[stage.name]]
    assert changed == _downstream_of("track")  # track and every stage reading what it made, nothing else
    assert changed[:2] == ["track", "aggregate"] and "lidar_rays" not in changed


def test_a_restored_blob_or_map_changes_its_scene_key_only(synthetic_root, tmp_path):
    data_root = tmp_path / "data"
    shutil.copytree(synthetic_root, data_root)
    dbs = resolve_logs(data_root, split=None)
    out = str(tmp_path / "out")

    def keys() -> dict[str, str]:
        tasks = plan_tasks(dbs, data_root, maps_root_for(data_root, None), out, default_work_root(out),
                           default_params(PIPELINE))
        return {task.scene_name: stage_keys(task, PIPELINE)["load"] for task in tasks}

    first = keys()
    blob = sorted((data_root / "nuplan-v1.1" / "sensor_blobs").rglob("*.pcd"))[0]
    content = blob.read_bytes()
    blob.unlink()
    missing = keys()
    blob.write_bytes(content)
    restored = keys()
    assert sum(first[s] != missing[s] for s in first) >= 1  # the scenes reading that blob (with its context)
    assert sum(first[s] != missing[s] for s in first) < len(first)  # not the others
    assert all(restored[s] != missing[s] for s in first if first[s] != missing[s])  # a restored file rebuilds
    maps = sorted(maps_root_for(data_root, None).rglob("map.gpkg"))
    assert maps, "the synthetic log has a map"
    maps[0].rename(maps[0].with_suffix(".moved"))
    assert all(keys()[s] != restored[s] for s in first)  # every scene of the log reads the map
