"""Repeated scale-bench builds: a row is the median of each cost figure, and the report lists every build."""

from __future__ import annotations

from benchmarks.scale import median_build, render_scale_markdown


def _build(cpu: float, peak: float, stages: dict[str, float], killed: str = "") -> dict:
    return {"cpu_seconds_per_frame": cpu, "seconds_per_frame": cpu + 0.1, "wall_seconds_per_frame": cpu + 0.2,
            "wall_seconds": 100 * cpu, "peak_rss_mb": peak, "stage_cpu_seconds_per_frame": stages,
            "stage_seconds_per_frame": stages, "stage_peak_rss_mb": {s: peak for s in stages}, "ok": not killed,
            "killed": killed, "frames_built": 200, "frames_failed": 0, "work_bytes_per_frame": 7.0,
            "dataset_bytes_per_frame": 9.0}


def test_median_of_three_builds_per_figure_and_stage():
    row = median_build([_build(1.5, 1200, {"load": 0.1, "write": 0.4}), _build(1.9, 1250, {"load": 0.3, "write": 0.2}),
                        _build(1.6, 1210, {"load": 0.2, "write": 0.3, "extra": 0.05})])
    assert row["cpu_seconds_per_frame"] == 1.6 and row["peak_rss_mb"] == 1210
    assert row["stage_cpu_seconds_per_frame"] == {"load": 0.2, "write": 0.3, "extra": 0.05}
    assert row["cpu_seconds_per_frame_builds"] == [1.5, 1.9, 1.6] and row["ok"] and row["killed"] == ""
    assert row["frames_built"] == 200 and row["dataset_bytes_per_frame"] == 9.0


def test_a_killed_build_marks_the_row_and_the_note_lists_every_build():
    row = median_build([_build(1.5, 1200, {"load": 0.1}), _build(1.7, 6100, {"load": 0.2}, killed="killed at 6100 MB")])
    assert not row["ok"] and row["killed"] == "killed at 6100 MB"
    report = {"software": "x", "machine": "y", "cpus": 2, "preset": "city", "seed": 0, "quality_frame_stride": 2,
              "runs": [{"seconds": 20.0, "code": "abc", "date": "2026-12-05 21:00 UTC", **row}]}
    assert "killed at 6100 MB; median of 2 interleaved builds: 1.500 / 1.700" in render_scale_markdown(report)
