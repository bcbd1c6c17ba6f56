"""Clips by output frame: `output_index` from timestamps (builds) and from frame_index (older manifests)."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.grid import GridSpec
from nuplan_occ.io.types import LidarFrame
from nuplan_occ.pipeline.scene import output_slots
from nuplan_occ.storage import DatasetWriter
from nuplan_occ.storage.clips import output_index_from_frame_index, output_index_from_timestamps
from nuplan_occ.synth.grid_frames import synthetic_log
from nuplan_occ.torch import OccupancyDataset

GRID = GridSpec(-2.0, 2.0, -2.0, 2.0, -1.0, 1.0, 0.25)
SWEEP_US = 50_000


def sweeps(n: int, dropped: tuple[int, ...] = (), jitter_us: int = 3_000) -> list[LidarFrame]:
    """A log's 20 Hz lidar_pc rows with the sweeps at `dropped` time slots missing (indices stay consecutive,
    as in a log that lost them); timestamps jitter by +-jitter_us."""
    rng = np.random.default_rng(0)
    slots = [k for k in range(n) if k not in dropped]
    return [LidarFrame(f"t{k}", 1_000_000 + k * SWEEP_US + int(rng.integers(-jitter_us, jitter_us + 1)), "", "s", "", "",
                       index=i) for i, k in enumerate(slots)]


def test_output_index_counts_output_periods_and_skips_missed_slots():
    t = np.array([0, 103_000, 198_000, 350_000, 452_000])  # 10 Hz, one sweep lost between the 3rd and 4th
    assert output_index_from_timestamps(t, 100_000, 25_000).tolist() == [0, 1, 2, 4, 5]
    t5 = np.array([0, 200_000, 450_000, 650_000, 1_050_000])  # 5 Hz: a lost sweep (+50 ms), then a lost frame
    assert output_index_from_timestamps(t5, 200_000, 25_000).tolist() == [0, 1, 3, 4, 6]
    assert output_index_from_timestamps(np.array([7]), 100_000, 25_000).tolist() == [0]


@pytest.mark.parametrize("rate_hz, expected", [
    (10.0, [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]),
    (5.0, [0, 1, 2, 3, 4]),
    (20.0, list(range(20))),
])
def test_output_slots_are_consecutive_at_any_rate(rate_hz, expected):
    slots = output_slots(sweeps(20), rate_hz, 20.0)
    assert sorted(slots.values()) == expected
    assert [s for _, s in sorted(slots.items(), key=lambda kv: int(kv[0][1:]))] == expected


def test_a_sweep_missing_from_the_log_breaks_the_output_sequence():
    frames = sweeps(21, dropped=(9,))  # indices after the loss are shifted by one sweep (50 ms late)
    slots = output_slots(frames, 10.0, 20.0)
    by_time = [slots[f.token] for f in frames if f.token in slots]
    assert by_time == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10]


def test_older_manifests_derive_output_index_from_frame_index_spacing():
    scenes = np.array([0, 0, 0, 0, 1, 1, 1])
    assert output_index_from_frame_index(scenes, np.array([0, 2, 6, 8, 10, 12, 14])).tolist() == [0, 1, 3, 4, 0, 1, 2]
    assert output_index_from_frame_index(scenes, np.array([0, 4, 8, 16, 20, 24, 28])).tolist() == [0, 1, 2, 4, 0, 1, 2]
    assert output_index_from_frame_index(scenes[:0], np.zeros(0, np.int64)).tolist() == []


def _write(root, records) -> str:
    writer = DatasetWriter(str(root), {"params": {}}, grid=GRID)
    writer.commit(writer.write_shard("a", records))
    return str(root)


def test_clips_follow_output_index_and_old_sweep_indexed_manifests_still_give_clips(tmp_path):
    # a build at 10 Hz: frame_index counts 20 Hz sweeps; output frame 3 of scene 0 failed
    records = synthetic_log(GRID, "log-a", 0, [6, 5], failed=[3])
    for i, record in enumerate(records):
        record.frame_index = 2 * i
    old = OccupancyDataset(_write(tmp_path / "old", records), clip_len=2)
    for record, slot in zip(records, [0, 1, 2, 3, 4, 5, 0, 1, 2, 3, 4]):
        record.columns["output_index"] = slot
    new = OccupancyDataset(_write(tmp_path / "new", records), clip_len=2)
    for occ in (old, new):
        starts = [occ.ds[int(occ.frame_indices(i)[0])]["frame_index"] for i in range(len(occ))]
        assert starts == [0, 2, 8, 12, 14, 16, 18]  # no clip across the failed frame 6 or the scene change at 12
    assert len(OccupancyDataset(str(tmp_path / "new"), clip_len=5)) == 1
