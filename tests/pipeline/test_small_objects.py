"""Objects near a voxel in size are never lost: on a synthetic log of cones (0.3, 0.4 m), bollards (0.2 m),
posts (0.25 m) and small boxes (0.5 m) that the ego passes at 1-15 m, every object is labeled in every
frame in which the LiDAR sees it, through a real build with the objects' default (torch) surfaces."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from nuplan_occ.dataset import open_dataset
from nuplan_occ.labels import LABELS
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.pipeline.params import apply_overrides
from nuplan_occ.storage import read_manifest
from nuplan_occ.stages import PIPELINE

from pipeline_helpers import build_params

pytestmark = pytest.mark.slow

SMALL_CLASSES = ("traffic_cone", "barrier", "generic_object")


@pytest.fixture(scope="module")
def small_objects_build(tmp_path_factory):
    from nuplan_occ.synth.generate import synthesize

    base = tmp_path_factory.mktemp("small_objects")
    synthesize(base / "data", logs=1, seconds=2.0, seed=3, preset="small_objects", scene_seconds=2.0)
    params = apply_overrides(build_params(fast=False), {"reconstruct": {"method": "none"},  # background: points
                                                        "load": {"context_seconds": 0.25}}, "test")
    run_build(base / "data", str(base / "out"), params, pipeline=PIPELINE)
    return base / "data", base / "out"


def seen_and_labeled(build, truth) -> dict[tuple[str, int], list[bool]]:
    """(class, truth instance) -> per frame in which the truth object has a LiDAR-observed voxel: whether
    the build has a voxel of its class within one voxel of the object's true voxels."""
    frames = {truth.get(i, keys=())["token"]: i for i in range(len(truth))}
    ids = [LABELS.id_of(name) for name in SMALL_CLASSES]
    result: dict[tuple[str, int], list[bool]] = {}
    for i in range(len(build)):
        built = build.get(i, keys=("semantics",))
        true = truth.get(frames[built["token"]], keys=("semantics", "instance", "mask_lidar"))
        small = np.isin(true["semantics"], ids)
        for k in np.unique(true["instance"][small]):
            voxels = true["instance"] == k
            if not (voxels & true["mask_lidar"]).any():
                continue
            label = int(np.bincount(true["semantics"][voxels]).argmax())
            index = np.argwhere(voxels)
            window = tuple(slice(max(lo - 1, 0), hi + 2) for lo, hi in zip(index.min(axis=0), index.max(axis=0)))
            near = ndimage.binary_dilation(voxels[window])
            result.setdefault((LABELS.names[label], int(k)), []).append(
                bool((built["semantics"][window][near] == label).any()))
    return result


def test_every_small_object_is_labeled_in_every_frame_it_is_seen(small_objects_build):
    data, out = small_objects_build
    labeled = seen_and_labeled(open_dataset(str(out)), open_dataset(str(data / "truth")))
    assert {name for name, _ in labeled} == set(SMALL_CLASSES)
    assert len(labeled) >= 10 and all(len(frames) >= 10 for frames in labeled.values())
    missed = {key: frames.count(False) for key, frames in labeled.items() if not all(frames)}
    assert not missed, f"objects unlabeled in some frames they are seen in: {missed}"
    rows = [r for r in read_manifest(str(out)).to_pylist() if r["status"] == "ok"]
    assert all(r["qa_boxes_labeled"] == r["qa_boxes_with_points"] for r in rows)
    assert sum(r["qa_boxes_with_points"] for r in rows) >= sum(len(f) for f in labeled.values())
