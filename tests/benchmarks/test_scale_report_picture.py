"""The scale report's picture: which builds it shows, their stage seconds, and the file the report links."""

from __future__ import annotations

import json

import matplotlib.pyplot as plt
import numpy as np

from benchmarks.scale import PICTURE_NAME, STAGE_ORDER, write_scale_report


def _run(seconds: float, code: str, stages: dict[str, float] | None, peak: float) -> dict:
    run = {"seconds": seconds, "code": code, "date": "2026-12-05 04:04 UTC", "frames_built": 10, "frames_failed": 0,
           "seconds_per_frame": 1.0, "wall_seconds_per_frame": 1.0, "peak_rss_mb": peak, "work_bytes_per_frame": 1.0,
           "dataset_bytes_per_frame": 1.0, "killed": "", "stage_seconds_per_frame": {}, "stage_peak_rss_mb": {}}
    if stages is not None:
        run["stage_cpu_seconds_per_frame"] = stages
        run["cpu_seconds_per_frame"] = sum(stages.values())
    return run


def test_picture_shows_the_20_s_builds_with_stage_seconds_and_the_report_links_it(tmp_path) -> None:
    from benchmarks.scale_plot import stage_history

    report = {"software": "x", "machine": "y", "cpus": 2, "preset": "city", "seed": 0, "quality_frame_stride": 2,
              "runs": [_run(20.0, "old", None, 3000.0),                       # no stage CPU recorded: left out
                       _run(5.0, "new", {"load": 0.1, "write": 0.2}, 900.0),  # other scene length: left out
                       _run(20.0, "new", {"write": 0.3, "load": 0.1, "extra": 0.05}, 1200.0),
                       _run(20.0, "base", {"load": 0.2, "reconstruct": 0.6}, 1300.0)]}
    history = stage_history(report, 20.0, STAGE_ORDER)
    assert [label.split()[0] for label in history.labels] == ["new", "base"]
    assert history.stages == ["load", "reconstruct", "write", "extra"]  # pipeline order, unknown stages last
    np.testing.assert_allclose(history.seconds, [[0.1, 0.0, 0.3, 0.05], [0.2, 0.6, 0.0, 0.0]])
    np.testing.assert_allclose(history.peak_mb, [1200.0, 1300.0])

    write_scale_report(report, tmp_path)
    image = plt.imread(tmp_path / PICTURE_NAME)
    assert image.shape[1] > 800 and image.shape[0] > 150
    assert f"]({PICTURE_NAME})" in (tmp_path / "report-scale.md").read_text()
    assert json.loads((tmp_path / "report-scale.json").read_text())["runs"][2]["code"] == "new"


def test_report_without_stage_seconds_has_no_picture(tmp_path) -> None:
    report = {"software": "x", "machine": "y", "cpus": 2, "preset": "city", "seed": 0, "quality_frame_stride": 2,
              "runs": [_run(20.0, "old", None, 3000.0)]}
    write_scale_report(report, tmp_path)
    assert not (tmp_path / PICTURE_NAME).exists()
    assert PICTURE_NAME not in (tmp_path / "report-scale.md").read_text()
