"""The README workspace: a folder laid out as README.md assumes, with its shared build (see readme_cases)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from readme_cases import CASES, README, REPO, is_shared_build, readme_files, run_command


@pytest.fixture(scope="session")
def readme_root(tmp_path_factory) -> Path:
    """The README's nuPlan data root: the suite's small 1.2 s log, written as ONE scene (12 output frames at
    10 Hz), so clips as long as the README's temporal DiT needs (7 frames) exist; the suite's shared
    `synthetic_root` splits the same log into 5 scenes of 2-3 frames."""
    from nuplan_occ.synth.generate import synthesize

    root = tmp_path_factory.mktemp("readme_synth") / "data"
    synthesize(root, logs=1, seconds=1.2, seed=7, preset="small", scene_seconds=1.2)
    return root


@pytest.fixture(scope="session")
def workspace(readme_root, tmp_path_factory):
    """(folder, environment) laid out as the README assumes; the shared build is made here."""
    folder = tmp_path_factory.mktemp("readme")
    for name, content in readme_files(README.read_text()).items():
        (folder / name).write_text(content)
    (folder / "truth").symlink_to(readme_root / "truth")
    env = {**os.environ, "NUPLAN_DATA_ROOT": str(readme_root), "COLUMNS": "100",
           "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    build = next(c for c in CASES if is_shared_build(c))
    result = run_command(build.text, folder, env)
    assert result.returncode == 0, f"{build.text}\n{result.stderr[-3000:]}"
    write_release_folder(folder / "out", folder / "RELEASE")
    write_predictions_folder(folder / "out", folder / "preds")
    return folder, env


def write_relabeled_frames(build: Path, target: Path, relabel: tuple[str, str]) -> None:
    """Every frame of the build as `<target>/<lidar_pc token>.npy` (uint8 [400, 400, 32]), with the voxels of
    class relabel[0] written as relabel[1]."""
    import numpy as np

    import nuplan_occ
    from nuplan_occ.labels import LABELS

    ds = nuplan_occ.open_dataset(str(build))
    target.mkdir(parents=True)
    for i in range(len(ds)):
        frame = ds.get(i, keys=("semantics",))
        semantics = frame["semantics"].copy()
        semantics[semantics == LABELS.id_of(relabel[0])] = LABELS.id_of(relabel[1])
        np.save(target / f"{frame['token']}.npy", semantics)


def write_predictions_folder(build: Path, preds: Path) -> None:
    """`preds/`: a model's predictions as `nuplan-occ eval` reads them, one `<token>.npy` per frame (our ids,
    our grid): the build's own semantics with every vehicle voxel turned into other, so the scores are not
    trivially perfect."""
    write_relabeled_frames(build, preds, ("vehicle", "other"))


def write_release_folder(build: Path, release: Path) -> None:
    """`RELEASE/`: the build's frames in the released Nuplan-Occ's dense layout
    (`nuplan_quantized_400_400_32/<lidar_pc token>.npy`, UniScenev2 ids), as a downloaded release would
    hold them for the same logs; other_ground, which the UniScenev2 palette lacks, is written as other."""
    write_relabeled_frames(build, release / "nuplan_quantized_400_400_32", ("other_ground", "other"))
