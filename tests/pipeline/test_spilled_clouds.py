"""The spilled scene clouds: what goes in comes back bit for bit, one sweep at a time, and no file is left."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.io.types import PointCloud
from nuplan_occ.pipeline.scene import Sweep
from nuplan_occ.pipeline.spilled_clouds import SpilledClouds


def random_cloud(rng: np.random.Generator, n: int) -> PointCloud:
    return PointCloud(rng.normal(size=(n, 3)).astype(np.float32), rng.random(n, dtype=np.float32),
                      rng.integers(0, 64, n).astype(np.int16), rng.integers(-1, 5, n).astype(np.int8), "ego")


def test_clouds_read_back_bit_for_bit_in_any_order_and_leave_no_file(tmp_path):
    rng = np.random.default_rng(3)
    clouds = [random_cloud(rng, n) for n in (1000, 0, 37, 5000)]
    store = SpilledClouds(tmp_path / "load")
    stored = [store.add(cloud) for cloud in clouds]
    assert list((tmp_path / "load").iterdir()) == []  # an unnamed file: nothing to clean up, even after a kill
    for k in (3, 0, 2, 1, 3):
        back = stored[k].read()
        assert len(stored[k]) == len(clouds[k]) and back.frame == "ego"
        for name in ("xyz", "intensity", "ring", "lidar_info"):
            np.testing.assert_array_equal(getattr(back, name), getattr(clouds[k], name))
            assert getattr(back, name).dtype == getattr(clouds[k], name).dtype
    np.testing.assert_array_equal(stored[0].field("xyz"), clouds[0].xyz)


def test_a_sweep_reads_its_points_on_each_access_and_says_why_it_has_none(tmp_path):
    rng = np.random.default_rng(4)
    cloud = random_cloud(rng, 10)
    stored = SpilledClouds(tmp_path).add(cloud)
    empty_boxes = None
    loaded = Sweep("a", 0, 0, np.eye(4), stored, empty_boxes, empty_boxes, True)
    failed = Sweep("b", 1, 50_000, np.eye(4), None, empty_boxes, empty_boxes, True, failure="b.pcd: truncated")
    first, second = loaded.xyz, loaded.xyz
    np.testing.assert_array_equal(first, cloud.xyz)
    assert first is not second  # a fresh copy each time: nothing of the scene stays referenced
    assert loaded.has_cloud and not failed.has_cloud and failed.cloud is None
    with pytest.raises(ValueError, match="truncated"):
        failed.xyz
