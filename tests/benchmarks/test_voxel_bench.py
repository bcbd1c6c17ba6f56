"""The benchmark's synthetic frame is realistic in size and frame_costs times every per-frame function."""

import numpy as np
import pytest

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import PEDESTRIAN, VEHICLE
from benchmarks.voxel_bench import frame_costs, synthetic_frame
from nuplan_occ.voxel.compose import compose_frame


def test_synthetic_frame_and_its_costs():
    frame = synthetic_frame(0)
    assert 80_000 <= len(frame.points_ego) <= 150_000 and len(frame.cameras) == 8
    assert all(abs(c.K[0, 0] - 1545.0) < 40 and (c.width, c.height) == (1920, 1080) for c in frame.cameras)
    idx, inside = DEFAULT_GRID.point_to_index(frame.points_ego)
    assert inside.mean() > 0.8  # most returns land in the grid
    grids = compose_frame(frame.background_vertices, frame.background_faces, frame.objects, None)
    classes = set(np.unique(grids.semantics).tolist())
    assert {VEHICLE, PEDESTRIAN} <= classes and (grids.semantics > 0).sum() > 100_000
    costs = frame_costs(frame.points_ego, frame.origin, grids.semantics > 0, frame.cameras, frame=frame, repeats=1)
    parts = {"lidar_visibility", "camera_visibility", "compose_frame", "rasterize_bev", "label_background"}
    assert set(costs) == parts | {"total"} and all(costs[k] > 0 for k in parts)
    assert costs["total"] == pytest.approx(sum(costs[k] for k in parts))
