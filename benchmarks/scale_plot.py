"""The scale report's picture (bench/report-scale.png): where the seconds of a frame go, build after build.

One bar per build of the chosen scene length that recorded CPU seconds per stage, in the order the bench ran
them (oldest at the top; a run builds its new code first, then its baseline), split
into its stages' CPU seconds per output frame, beside that build's peak RSS; the scale targets are
drawn as lines (1.0 s per frame, 6 GB).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

TARGET_SECONDS_PER_FRAME = 1.0
TARGET_PEAK_MB = 6000.0
STAGE_COLORS = plt.get_cmap("tab20").colors
"""One colour per stage, in pipeline order."""


@dataclass(frozen=True)
class StageHistory:
    """labels (B,): "code date" of each build; stages (S,): stage names in pipeline order; seconds (B, S):
    CPU seconds per output frame of each stage (0 where a build has no such stage); peak_mb (B,)."""

    labels: list[str]
    stages: list[str]
    seconds: np.ndarray
    peak_mb: np.ndarray


def stage_history(report: dict, scene_seconds: float, stage_order: list[str]) -> StageHistory:
    """The builds of `scene_seconds` in report["runs"] (scale report JSON) that recorded CPU seconds per
    stage, in the report's order; stages named in stage_order come in that order, any others after them."""
    runs = [r for r in report["runs"] if r["seconds"] == scene_seconds and r.get("stage_cpu_seconds_per_frame")]
    found = {s for r in runs for s in r["stage_cpu_seconds_per_frame"]}
    stages = [s for s in stage_order if s in found] + sorted(found - set(stage_order))
    seconds = np.array([[r["stage_cpu_seconds_per_frame"].get(s, 0.0) for s in stages] for r in runs], dtype=float)
    return StageHistory([f"{r['code']}  {r['date'][:16]}" for r in runs], stages,
                        seconds.reshape(len(runs), len(stages)), np.array([r["peak_rss_mb"] for r in runs], dtype=float))


def plot_stage_history(history: StageHistory, scene_seconds: float, path: Path) -> None:
    """Write the picture of `history` (module doc) to path (PNG)."""
    count = max(len(history.labels), 1)
    fig, (bars, peaks) = plt.subplots(1, 2, figsize=(12.0, 0.32 * count + 1.8), sharey=True,
                                      gridspec_kw={"width_ratios": [3.2, 1.0]})
    rows = np.arange(len(history.labels))
    left = np.zeros(len(history.labels))
    for k, stage in enumerate(history.stages):
        bars.barh(rows, history.seconds[:, k], left=left, color=STAGE_COLORS[k % len(STAGE_COLORS)], label=stage,
                  edgecolor="white", linewidth=0.4)
        left += history.seconds[:, k]
    for row, total in zip(rows, left):
        bars.text(total, row, f" {total:.2f}", va="center", fontsize=7)
    bars.axvline(TARGET_SECONDS_PER_FRAME, color="#d9534f", linestyle="--", linewidth=1)
    bars.set_xlabel(f"CPU s per output frame, {scene_seconds:g} s city scene, one thread (red: target "
                    f"{TARGET_SECONDS_PER_FRAME:g} s)", fontsize=8)
    bars.set_yticks(rows, history.labels, fontsize=7)
    bars.invert_yaxis()
    bars.legend(fontsize=6, ncol=7, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    peaks.barh(rows, history.peak_mb, color="#7a8fa6")
    for row, peak in zip(rows, history.peak_mb):
        peaks.text(peak, row, f" {peak:.0f}", va="center", fontsize=7)
    peaks.set_xlim(0, max(TARGET_PEAK_MB, float(history.peak_mb.max(initial=0.0))) * 1.05)
    peaks.axvline(TARGET_PEAK_MB, color="#d9534f", linestyle="--", linewidth=1)
    peaks.set_xlabel(f"peak RSS MB (red: target {TARGET_PEAK_MB:g})", fontsize=8)
    for ax in (bars, peaks):
        ax.tick_params(labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
