"""Side-by-side benchmark of the reconstruction methods (for `make bench`).

`compare_methods` runs `reconstruct` per method on the same input and scores the result against
truth samples with `surface_metrics`. Peak memory is the peak process RSS above the RSS at the
start of the method (sampled every 10 ms; covers torch, Open3D and pymeshlab allocations, which
tracemalloc cannot see). `python -m benchmarks.recon_bench [half_extent_m]` runs it on the
synthetic street scene of `synthetic.street_scan`.
"""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import psutil

from nuplan_occ.recon.api import reconstruct
from nuplan_occ.evaluation.surfaces import surface_metrics
from nuplan_occ.recon.params import ReconParams

SAMPLE_SPACING = 0.05
"""Spacing (m) of the surface samples scored against the truth (below the 0.1 m threshold)."""


@contextmanager
def peak_rss_mb(period: float = 0.01) -> Iterator[dict]:
    """Context yielding a dict whose "peak_mb" is set, on exit, to the peak RSS increase (MB)."""
    process = psutil.Process()
    base = process.memory_info().rss
    state = {"peak": base, "run": True}

    def sample() -> None:
        while state["run"]:
            state["peak"] = max(state["peak"], process.memory_info().rss)
            time.sleep(period)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    out: dict = {}
    try:
        yield out
    finally:
        state["run"] = False
        thread.join()
        state["peak"] = max(state["peak"], process.memory_info().rss)
        out["peak_mb"] = (state["peak"] - base) / 2**20


def compare_methods(
    points: np.ndarray,
    origins: np.ndarray,
    truth_points: np.ndarray,
    methods: tuple[str, ...] = ("nksr", "poisson", "none"),
    params: ReconParams | None = None,
) -> list[dict]:
    """Per method: time_s, peak_mb, points_per_s, faces, and the `surface_metrics` of the result
    (Chamfer, precision / recall / F-score at 0.1 and 0.25 m). All arrays in one frame, metres."""
    rows = []
    for method in methods:
        with peak_rss_mb() as memory:
            start = time.perf_counter()
            surface = reconstruct(points, origins, method=method, params=params)
            elapsed = time.perf_counter() - start
        metrics = surface_metrics(surface.sample_points(SAMPLE_SPACING), truth_points)
        rows.append({
            "method": method,
            "time_s": elapsed,
            "peak_mb": memory["peak_mb"],
            "points_per_s": len(points) / max(elapsed, 1e-9),
            "faces": len(surface.faces),
            **metrics,
        })
    return rows


def format_table(rows: list[dict]) -> str:
    """The rows of `compare_methods` as a fixed-width text table."""
    keys = ["method", "time_s", "peak_mb", "points_per_s", "faces", "chamfer",
            "precision@0.1", "recall@0.1", "fscore@0.1", "precision@0.25", "recall@0.25", "fscore@0.25"]
    lines = [" ".join(f"{k:>14}" for k in keys)]
    for row in rows:
        lines.append(" ".join(f"{row[k]:>14.4g}" if not isinstance(row[k], str) else f"{row[k]:>14}" for k in keys))
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    """Benchmark on the synthetic street scene of half extent argv[0] metres (default 50)."""
    from nuplan_occ.synth.surface_scans import street_scan

    half = float(argv[0]) if argv else 50.0
    scan = street_scan(half=half, sweeps_per_street=max(4, int(half / 4)))
    print(f"street scene {2 * half:.0f} m x {2 * half:.0f} m: {len(scan.points)} points, {len(scan.truth_points)} truth samples")
    print(format_table(compare_methods(scan.points, scan.origins, scan.truth_points)))


if __name__ == "__main__":
    main(sys.argv[1:])
