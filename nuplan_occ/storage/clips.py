"""Clip and subset selection from manifest columns alone (no shard is opened).

A clip is `clip_len` frames of one scene with consecutive `frame_index` (a failed or missing frame
breaks the run). Within every maximal run, clip starts are the run's first frame and every `stride`-th
frame after it while the whole clip fits. Subsets follow the paper's spatio-temporal disentangled data
construction (UniScenev2, "Disentangled Data Construction"), per frame:
    spatial:  ego_speed > theta_e
    temporal: ego_speed < theta_e and max_agent_speed > theta_o
(speeds in m/s). A clip is in a subset iff every one of its frames is; null speeds are in no subset.
"""

from __future__ import annotations

import numpy as np

SUBSETS = ("spatial", "temporal")


def clip_order(scene_codes: np.ndarray, frame_index: np.ndarray) -> np.ndarray:
    """Row indices sorted by (scene, frame_index): clips are windows of this order."""
    return np.lexsort((frame_index, scene_codes))


def clip_starts(scene_codes: np.ndarray, frame_index: np.ndarray, order: np.ndarray, clip_len: int,
                stride: int) -> np.ndarray:
    """Positions p in `order` such that order[p : p + clip_len] is a clip (see module docstring)."""
    if clip_len < 1 or stride < 1:
        raise ValueError(f"clip_len ({clip_len}) and stride ({stride}) must be >= 1")
    scenes, frames = scene_codes[order], frame_index[order]
    n = len(order)
    breaks = np.ones(n, dtype=bool)
    if n:
        breaks[1:] = (scenes[1:] != scenes[:-1]) | (frames[1:] != frames[:-1] + 1)
    run_start = np.flatnonzero(breaks)
    run_end = np.append(run_start[1:], n)
    starts = [np.arange(a, b - clip_len + 1, stride) for a, b in zip(run_start, run_end) if b - a >= clip_len]
    return np.concatenate(starts).astype(np.int64) if starts else np.zeros(0, dtype=np.int64)


def subset_flags(subset: str, ego_speed: np.ndarray, max_agent_speed: np.ndarray, theta_e: float,
                 theta_o: float) -> np.ndarray:
    """Per-frame membership (bool) of `subset`; NaN speeds give False."""
    if subset == "spatial":
        return ego_speed > theta_e
    if subset == "temporal":
        return (ego_speed < theta_e) & (max_agent_speed > theta_o)
    raise ValueError(f"subset {subset!r} is not one of {SUBSETS}")


def clips_all_flagged(flags: np.ndarray, order: np.ndarray, starts: np.ndarray, clip_len: int) -> np.ndarray:
    """Bool per start: every frame of the clip has its flag set."""
    bad = np.concatenate([[0], np.cumsum(~flags[order])])
    return bad[starts + clip_len] - bad[starts] == 0
