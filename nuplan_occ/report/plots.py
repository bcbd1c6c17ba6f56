"""The scene page's plots (matplotlib, Agg, PNG): QA figures over the scene's time and its class histogram."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


@dataclass(frozen=True)
class Series:
    """One panel: values (F,) over the scene's frames (NaN where a frame lacks it), its y label, and an
    optional threshold line (value, label) the flag rule draws."""

    label: str
    values: np.ndarray
    threshold: tuple[float, str] | None = None


def plot_timeline(seconds: np.ndarray, series: list[Series], failed: np.ndarray, flagged: np.ndarray,
                  path: Path) -> None:
    """Stacked panels of `series` over `seconds` (s since the scene's first frame); failed frames are red
    bands, flagged frames orange ticks on every panel. Panels without a finite value say so."""
    half = 0.5 * float(np.median(np.diff(seconds))) if len(seconds) > 1 else 0.05
    fig, axes = plt.subplots(len(series), 1, figsize=(8.0, 1.55 * len(series) + 0.5), sharex=True, squeeze=False)
    for ax, s in zip(axes[:, 0], series):
        finite = np.isfinite(s.values)
        if finite.any():
            ax.plot(seconds[finite], s.values[finite], marker="o", markersize=2.5, linewidth=1.2, color="#1f5fa8")
        else:
            ax.text(0.5, 0.5, "not recorded in this build", transform=ax.transAxes, ha="center", va="center",
                    color="#888")
        if s.threshold is not None and np.isfinite(s.threshold[0]):
            ax.axhline(s.threshold[0], color="#d9534f", linestyle="--", linewidth=1)
            ax.text(1.0, s.threshold[0], f" {s.threshold[1]}", transform=ax.get_yaxis_transform(), va="center",
                    fontsize=7, color="#d9534f")
        for t in seconds[failed]:
            ax.axvspan(t - half, t + half, color="#d9534f", alpha=0.3, linewidth=0)
        for t in seconds[flagged & ~failed]:
            ax.axvline(t, color="#f0ad4e", alpha=0.5, linewidth=1)
        ax.set_ylabel(s.label, fontsize=8, rotation=0, ha="right", va="center")
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("seconds since the scene's first frame (red: failed frame, orange: flagged)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_class_histogram(counts: np.ndarray, names: dict[int, str], colors: dict[int, tuple[int, int, int]],
                         path: Path) -> None:
    """Horizontal bars of the scene's voxels per occupied class (label id > 0), in the label palette, as a
    share of the occupied voxels (log scale, so small classes stay visible)."""
    ids = [i for i in np.flatnonzero(counts).tolist() if i > 0]
    fig, ax = plt.subplots(figsize=(5.0, 0.32 * max(len(ids), 1) + 0.9))
    occupied = max(int(counts[1:].sum()), 1)
    if ids:
        shares = [100.0 * counts[i] / occupied for i in ids]
        ax.barh(range(len(ids)), shares, color=[np.array(colors.get(i, (0, 0, 0))) / 255 for i in ids],
                edgecolor="#333", linewidth=0.5)
        ax.set_yticks(range(len(ids)), [f"{names.get(i, i)} ({i})" for i in ids], fontsize=8)
        ax.set_xscale("log")
        for k, share in enumerate(shares):
            ax.text(share, k, f" {share:.2g}%", va="center", fontsize=7)
        ax.invert_yaxis()
    else:
        ax.text(0.5, 0.5, "no occupied voxel", transform=ax.transAxes, ha="center")
    ax.set_xlabel("% of the scene's occupied voxels (all ok frames)", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
