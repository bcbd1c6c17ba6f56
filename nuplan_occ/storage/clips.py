"""Clip and subset selection from manifest columns alone (no shard is opened).

A clip is `clip_len` ok frames of one scene with consecutive `output_index` (a failed or missing frame
breaks the run). `output_index` numbers a scene's output frames at the build's rate from 0 (10 Hz: one
step per 0.1 s); consecutive output frames get consecutive numbers, and a longer time gap between two
of them (a sweep missing from the log) skips the slots it missed (`output_index_from_timestamps`).
Manifests written before the column existed get it from `frame_index` (`output_index_from_frame_index`).
Within every maximal run, clip starts are the run's first frame and every `stride`-th frame after it
while the whole clip fits. Subsets follow the paper's spatio-temporal disentangled data
construction (UniScenev2, "Disentangled Data Construction"), per frame:
    spatial:  ego_speed > theta_e
    temporal: ego_speed < theta_e and max_agent_speed > theta_o
(speeds in m/s). A clip is in a subset iff every one of its frames is; null speeds are in no subset.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.storage import keyorder

SUBSETS = ("spatial", "temporal")


def output_index_from_timestamps(timestamps_us: np.ndarray, period_us: float, tolerance_us: float) -> np.ndarray:
    """(F,) int64 output index of one scene's output frames, given their timestamps (F,) us in time order.

    period_us: the output period (100 000 us at 10 Hz). A gap between consecutive output frames longer
    than period_us + tolerance_us (the build uses half a sweep period, 25 000 us at 20 Hz) means output
    slots were missed (a sweep missing from the log) and advances the index by round(gap / period), at
    least 2; any other gap advances it by 1."""
    t = np.asarray(timestamps_us, dtype=np.int64)
    if len(t) < 2:
        return np.zeros(len(t), dtype=np.int64)
    gaps = np.diff(t).astype(np.float64)
    missed = gaps > period_us + tolerance_us
    steps = np.where(missed, np.maximum(2, np.round(gaps / period_us)), 1).astype(np.int64)
    return np.concatenate([[0], np.cumsum(steps)])


def output_index_from_frame_index(scene_codes: np.ndarray, frame_index: np.ndarray) -> np.ndarray:
    """(N,) int64 output index for manifests without the column: frame_index // step minus its scene's
    smallest, step being the gcd of the frame_index differences of neighbours within scenes (2 for a
    10 Hz build of 20 Hz sweeps, 4 at 5 Hz). A failed frame that is absent still leaves its gap."""
    scene_codes, frame_index = np.asarray(scene_codes), np.asarray(frame_index, dtype=np.int64)
    order = clip_order(scene_codes, frame_index)
    same_scene = scene_codes[order][1:] == scene_codes[order][:-1]
    gaps = np.diff(frame_index[order])[same_scene]
    step = int(np.gcd.reduce(gaps[gaps > 0])) if (gaps > 0).any() else 1
    slots = frame_index // step
    first = np.full(int(scene_codes.max()) + 1 if len(scene_codes) else 0, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(first, scene_codes, slots)
    return slots - first[scene_codes]


def clip_order(scene_codes: np.ndarray, output_index: np.ndarray) -> np.ndarray:
    """Row indices (int64) stably sorted by (scene, output_index): clips are windows of this order."""
    return keyorder.lex_order([np.asarray(scene_codes), np.asarray(output_index)])


def clip_starts(scene_codes: np.ndarray, output_index: np.ndarray, order: np.ndarray, clip_len: int,
                stride: int) -> np.ndarray:
    """Positions p in `order` such that order[p : p + clip_len] is a clip (see module docstring)."""
    if clip_len < 1 or stride < 1:
        raise ValueError(f"clip_len ({clip_len}) and stride ({stride}) must be >= 1")
    scenes, frames = scene_codes[order], output_index[order]
    n = len(order)
    breaks = np.ones(n, dtype=bool)
    if n:
        breaks[1:] = (scenes[1:] != scenes[:-1]) | (frames[1:] != frames[:-1] + 1)
    run_start = np.flatnonzero(breaks)
    run_length = np.append(run_start[1:], n) - run_start
    per_run = np.where(run_length >= clip_len, (run_length - clip_len) // stride + 1, 0)
    first_of_run = np.cumsum(per_run) - per_run
    within = np.arange(int(per_run.sum()), dtype=np.int64) - np.repeat(first_of_run, per_run)
    return np.repeat(run_start, per_run).astype(np.int64) + within * stride


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
