"""`nuplan_occ.torch.OccupancyDataset`: clips inside scenes, relative poses, subsets, DataLoader workers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nuplan_occ.geometry import make_transform, yaw_matrix
from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import DatasetWriter, MissingMemberError
from nuplan_occ.storage.clips import clip_starts
from nuplan_occ.storage.reader import ShardReader
from nuplan_occ.synth.grid_frames import synthetic_log
from nuplan_occ.torch import OccupancyDataset

GRID = GridSpec(-2.0, 2.0, -2.0, 2.0, -1.0, 1.0, 0.25)  # 16 x 16 x 8
NAN = float("nan")


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """log-a: scenes of 5 and 4 frames, frame 2 failed; log-b: one scene of 6 frames, yawing."""
    root = tmp_path_factory.mktemp("clips")
    a = synthetic_log(GRID, "log-a", 0, [5, 4], ego_speeds=[0.2] * 9,
                      max_agent_speeds=[5, 5, 5, 5, 5, 5, 0.5, 5, 5], members=["semantics", "mask_lidar"], failed=[2])
    b = synthetic_log(GRID, "log-b", 1, [6], ego_speeds=[0.5, 0.5, 0.5, 3, 3, NAN],
                      max_agent_speeds=[3, 3, 0, 3, 3, 3], members=["semantics", "mask_lidar"])
    for t, record in enumerate(b):
        record.ego_to_global = make_transform(yaw_matrix(0.3 * t), np.array([100.0 + 2 * t, 50.0 - t, 1.0]))
    writer = DatasetWriter(str(root), {"params": {}}, grid=GRID)
    writer.commit(writer.write_shard("a", a) + writer.write_shard("b", b))
    return str(root)


def _clip_ids(occ: OccupancyDataset) -> list[tuple[str, int]]:
    """(log, first frame_index) of every clip."""
    logs = occ.ds.manifest["log"].to_pylist()
    frames = occ.ds.manifest["frame_index"].to_pylist()
    return [(logs[occ.frame_indices(i)[0]], frames[occ.frame_indices(i)[0]]) for i in range(len(occ))]


@pytest.mark.parametrize("clip_len, stride, expected", [
    (3, 1, [("log-a", 5), ("log-a", 6), ("log-b", 0), ("log-b", 1), ("log-b", 2), ("log-b", 3)]),
    (3, 2, [("log-a", 5), ("log-b", 0), ("log-b", 2)]),
    (2, 1, [("log-a", 0), ("log-a", 3), ("log-a", 5), ("log-a", 6), ("log-a", 7)]
           + [("log-b", i) for i in range(5)]),
    (1, 1, [("log-a", i) for i in (0, 1, 3, 4, 5, 6, 7, 8)] + [("log-b", i) for i in range(6)]),
])
def test_clips_never_cross_scenes_or_gaps(root, clip_len, stride, expected):
    occ = OccupancyDataset(root, clip_len=clip_len, stride=stride)
    assert sorted(_clip_ids(occ)) == expected
    scenes = occ.ds.manifest["scene_token"].to_pylist()
    frames = occ.ds.manifest["frame_index"].to_pylist()
    for i in range(len(occ)):
        rows = occ.frame_indices(i)
        assert len({scenes[r] for r in rows}) == 1
        assert [frames[r] for r in rows] == list(range(frames[rows[0]], frames[rows[0]] + clip_len))


def test_clip_starts_edge_cases():
    scenes = np.array([0, 0, 0, 1, 1])
    frames = np.array([0, 1, 2, 3, 4])
    order = np.arange(5)
    assert clip_starts(scenes, frames, order, 4, 1).tolist() == []
    assert clip_starts(scenes, frames, order, 2, 1).tolist() == [0, 1, 3]
    assert clip_starts(scenes[:0], frames[:0], order[:0], 1, 1).tolist() == []
    with pytest.raises(ValueError):
        clip_starts(scenes, frames, order, 0, 1)


def test_subsets_follow_the_speed_thresholds(root):
    spatial = OccupancyDataset(root, clip_len=2, subset="spatial")
    temporal = OccupancyDataset(root, clip_len=2, subset="temporal")
    # log-b ego speeds 0.5 0.5 0.5 3 3 nan, agents 3 3 0 3 3 3; log-a ego 0.2, agents 5 except frame 6
    assert _clip_ids(spatial) == [("log-b", 3)]
    assert _clip_ids(temporal) == [("log-a", 0), ("log-a", 3), ("log-a", 7), ("log-b", 0)]
    assert _clip_ids(OccupancyDataset(root, clip_len=2, subset="temporal", theta_o=4.0)) == [
        ("log-a", 0), ("log-a", 3), ("log-a", 7)]
    assert _clip_ids(OccupancyDataset(root, clip_len=1, subset="spatial", theta_e=0.3)) == [
        ("log-b", i) for i in range(5)]
    with pytest.raises(ValueError, match="subset"):
        OccupancyDataset(root, subset="fast")


def test_items_stack_frames_and_poses_are_relative_to_the_first(root):
    occ = OccupancyDataset(root, clip_len=3, stride=3, keys=("semantics", "mask_lidar"))
    item = occ[len(occ) - 1]  # log-b frames 3, 4, 5
    assert item["log_name"] == "log-b" and item["frame_index"].tolist() == [3, 4, 5]
    assert item["semantics"].shape == (3, 16, 16, 8) and item["semantics"].dtype == torch.uint8
    assert item["mask_lidar"].dtype == torch.bool and item["poses"].dtype == torch.float64
    frames = [occ.ds[int(r)] for r in occ.frame_indices(len(occ) - 1)]
    for t, frame in enumerate(frames):
        np.testing.assert_array_equal(item["semantics"][t].numpy(), frame["semantics"])
        expected = np.linalg.inv(frames[0]["ego_to_global"]) @ frame["ego_to_global"]
        np.testing.assert_allclose(item["poses"][t].numpy(), expected, atol=1e-9)
    np.testing.assert_allclose(item["poses"][0].numpy(), np.eye(4), atol=1e-12)
    # frame 4 relative to frame 3: yaw +0.3 rad, and the step (2, -1) m rotated into frame 3's axes
    step = yaw_matrix(-0.9) @ np.array([2.0, -1.0, 0.0])
    np.testing.assert_allclose(item["poses"][1, :3, 3].numpy(), step, atol=1e-9)
    np.testing.assert_allclose(item["poses"][1, :3, :3].numpy(), yaw_matrix(0.3), atol=1e-9)
    with pytest.raises(MissingMemberError):
        OccupancyDataset(root, keys=("flow",))[0]


def test_dataloader_with_two_workers(root):
    occ = OccupancyDataset(root, clip_len=2, keys=("semantics", "mask_lidar"))
    expected = [occ[i] for i in range(len(occ))]  # opens shard handles in the parent before the fork
    loader = torch.utils.data.DataLoader(occ, batch_size=2, num_workers=2, shuffle=False)
    got = [batch for batch in loader]
    assert sum(len(b["semantics"]) for b in got) == len(occ) == 10
    flat = [(b, j) for b in got for j in range(len(b["semantics"]))]
    for (batch, j), item in zip(flat, expected):
        assert torch.equal(batch["semantics"][j], item["semantics"])
        assert torch.equal(batch["mask_lidar"][j], item["mask_lidar"])
        assert torch.equal(batch["poses"][j], item["poses"])
        assert batch["scene_token"][j] == item["scene_token"]


def test_a_clip_in_one_shard_costs_one_read(root, monkeypatch):
    calls = []
    original = ShardReader._read

    def counting(self, shard, start, length):
        calls.append((shard, start, length))
        return original(self, shard, start, length)

    monkeypatch.setattr(ShardReader, "_read", counting)
    occ = OccupancyDataset(root, clip_len=4, keys=("semantics", "mask_lidar"))
    item = occ[len(occ) - 1]
    assert item["semantics"].shape[0] == 4 and len(calls) == 1 and calls[0][0] == "b"
