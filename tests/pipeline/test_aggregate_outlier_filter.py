"""A long scene's outlier test runs once on its aggregate (FilterParams.aggregate_min_sweeps), through a real
build: the synthetic log built with every scene counted as long against the shared build, which filters its
short scenes sweep by sweep. Both are scored against the log's exact truth."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.evaluation.datasets import evaluate
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.pipeline.params import apply_overrides
from nuplan_occ.storage import read_manifest
from nuplan_occ.stages import PIPELINE

from pipeline_helpers import build_params

pytestmark = pytest.mark.slow


def test_filtering_on_the_aggregate_keeps_the_build_whole_and_as_good(synthetic_root, reference_build, tmp_path):
    out = tmp_path / "out"
    run_build(synthetic_root, str(out), apply_overrides(build_params(), {"filter": {"aggregate_min_sweeps": 1}}, "test"), pipeline=PIPELINE)
    rows, reference = read_manifest(str(out)).to_pylist(), read_manifest(str(reference_build)).to_pylist()
    assert [r["status"] for r in rows] == [r["status"] for r in reference] and {r["status"] for r in rows} == {"ok"}
    # the points the aggregate's test removed are counted against the sweeps they came from
    assert sum(r["qa_outliers_removed"] for r in rows) > 0
    assert np.mean([r["qa_pose_accepted"] for r in rows]) >= np.mean([r["qa_pose_accepted"] for r in reference]) - 0.1
    deferred, per_sweep = (evaluate(str(build), str(synthetic_root / "truth"))["pooled"] for build in (out, reference_build))
    assert deferred["iou"] >= per_sweep["iou"] - 0.01 and deferred["miou"] >= per_sweep["miou"] - 0.02
