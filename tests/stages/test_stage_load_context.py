"""Context sweeps around a scene (load stage)."""

from __future__ import annotations

from nuplan_occ.io.types import LidarFrame
from nuplan_occ.stages.load import context_frames


def _frames(n: int) -> list[LidarFrame]:
    """n frames at 20 Hz, scenes of 10 frames."""
    return [LidarFrame(f"{i:04x}", 1_000_000 + 50_000 * i, f"f{i}.pcd", f"s{i // 10}", "", "l", None, None, i)
            for i in range(n)]


def test_context_adds_every_strided_frame_within_the_window_on_both_sides():
    log = _frames(40)
    own = log[10:20]
    out = context_frames(log, own, seconds=0.3, stride=2)
    assert [f.index for f in out] == [4, 6, 8, *range(10, 20), 20, 22, 24]
    assert [f.timestamp_us for f in out] == sorted(f.timestamp_us for f in out)


def test_no_context_and_log_edges():
    log = _frames(40)
    assert context_frames(log, log[10:20], seconds=0.0, stride=2) == log[10:20]
    assert [f.index for f in context_frames(log, log[0:10], seconds=0.2, stride=1)] == list(range(0, 14))
    assert context_frames(log, [], seconds=1.0, stride=2) == []
