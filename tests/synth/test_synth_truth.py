"""Truth of a synthetic world against analytic geometry; LiDAR returns against the world's surfaces."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import shapely
from shapely.geometry import box

from nuplan_occ.grid import DEFAULT_GRID as GRID
from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE
from nuplan_occ.synth.agents import mesh_template, shape_parts
from nuplan_occ.synth.lidar import T_EGO_FROM_LIDAR, sweep_at
from nuplan_occ.synth.presets import SynthOptions, get_preset
from nuplan_occ.synth.truth import semantic_truth, truth_for_frame
from nuplan_occ.synth.world import build_world

START_US = 1_620_856_838_000_000


@pytest.fixture(scope="module")
def world():
    return build_world(get_preset("small"), SynthOptions(), seed=1, log_index=0, duration=3.0, start_us=START_US)


@pytest.fixture(scope="module")
def frame(world):
    t_us = START_US + 1_500_000
    T = world.true_pose(t_us)
    return t_us, T, truth_for_frame(world, t_us, T)


def _to_ego(world, T_global_from_ego, xy_local):
    T = world.local_from_global(T_global_from_ego)
    c, s = T[0, 0], T[1, 0]
    d = np.asarray(xy_local) - T[:2, 3]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1), np.arctan2(s, c), T[2, 3]


def _part_voxels(xy: np.ndarray, rel_yaw: float, z_center: float, lo: np.ndarray, hi: np.ndarray) -> set:
    """Voxels (i, j, k) of the grid that a solid cuboid part [lo, hi] (box frame) of a box at ego xy, yaw
    rel_yaw and centre height z_center intersects (shapely polygons against voxel squares, z by index)."""
    u, v = np.array([np.cos(rel_yaw), np.sin(rel_yaw)]), np.array([-np.sin(rel_yaw), np.cos(rel_yaw)])
    poly = shapely.Polygon([xy + a * u + b * v for a, b in ((lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1]))])
    x0, y0, x1, y1 = poly.bounds
    cols = [(i, j) for i in range(int(np.floor((x0 - GRID.x_min) / 0.25)), int(np.floor((x1 - GRID.x_min) / 0.25)) + 1)
            for j in range(int(np.floor((y0 - GRID.y_min) / 0.25)), int(np.floor((y1 - GRID.y_min) / 0.25)) + 1)
            if poly.intersects(box(GRID.x_min + i * 0.25, GRID.y_min + j * 0.25, GRID.x_min + (i + 1) * 0.25, GRID.y_min + (j + 1) * 0.25))]
    k0 = int(np.floor((z_center + lo[2] - GRID.z_min) / 0.25))
    k1 = min(int(np.floor((z_center + hi[2] - GRID.z_min) / 0.25)), GRID.shape[2] - 1)
    return {(i, j, k) for i, j in cols for k in range(k0, k1 + 1)}


def test_box_object_fills_exactly_its_parts(world, frame):
    t_us, T, truth = frame
    t = float(world.seconds(t_us))
    checked, kinds = 0, set()
    for agent in world.agents:
        center, yaw, _ = agent.state(np.array([t]))
        xy, ego_yaw, ego_z = _to_ego(world, T, center[0, :2])
        if np.max(np.abs(xy)) > 40:
            continue
        parts = shape_parts(agent.category, agent.size)
        assert np.all(parts[:, 0] >= -agent.size / 2 - 1e-12) and np.all(parts[:, 1] <= agent.size / 2 + 1e-12)
        expected = set().union(*(_part_voxels(xy, yaw[0] - ego_yaw, center[0, 2] - ego_z, lo, hi) for lo, hi in parts))
        got = {tuple(int(v) for v in idx) for idx in np.argwhere(truth["instance"] == agent.instance)}
        assert got == expected, (agent.category, agent.instance)
        assert np.all(truth["semantics"][truth["instance"] == agent.instance] == agent.label)
        checked += 1
        kinds.add(agent.category)
    assert checked >= 5 and "vehicle" in kinds


def test_vehicle_truth_is_not_its_box():
    """A vehicle's solid is body + cabin + wheels: the space under the body between the wheels and beside
    the cabin is empty, and the mesh is the parts' surfaces."""
    size = np.array([4.5, 2.0, 1.6])
    parts = shape_parts("vehicle", size)
    inside = lambda p: bool(np.any(np.all((parts[:, 0] <= p) & (p <= parts[:, 1]), axis=1)))
    assert inside(np.array([0.0, 0.0, 0.0])) and not inside(np.array([0.0, 0.0, -0.75]))
    assert not inside(np.array([2.0, 0.95, 0.75])) and inside(np.array([0.0, 0.0, 0.75]))
    tris = mesh_template("vehicle", size)
    assert tris.shape == (12 * len(parts), 3, 3)
    assert np.all(tris >= -size / 2 - 1e-12) and np.all(tris <= size / 2 + 1e-12)


def test_ground_is_one_layer_at_ground_height(frame):
    _, _, truth = frame
    # the TRUE ego origin is 0.36 m above the ground: road at ego z = -0.36 (layer 10, [-0.5, -0.25));
    # walkways 0.15 m higher at z = -0.21 (layer 11)
    road = np.isin(truth["semantics"], [ROAD, ROAD_LINE])
    assert set(np.unique(np.nonzero(road)[2]).tolist()) == {10}
    walkway = truth["semantics"] == OTHER_GROUND
    assert set(np.unique(np.nonzero(walkway)[2]).tolist()) <= {10, 11}
    # every column is covered by ground or something above it (the world is larger than the grid)
    assert np.all(truth["semantics"].any(axis=2))


def test_paint_follows_the_boundaries(world, frame):
    t_us, T, truth = frame
    lines = shapely.union_all(world.net.boundaries)
    idx = np.argwhere(truth["semantics"] == ROAD_LINE)
    centers = GRID.index_to_center(idx)
    T_local = world.local_from_global(T)
    local = centers[:, :2] @ T_local[:2, :2].T + T_local[:2, 3]
    dist = shapely.distance(lines, shapely.points(local))
    # a road_line voxel overlaps a 0.15 m strip: its centre is within 0.075 + half a voxel diagonal
    assert len(idx) > 100 and np.max(dist) <= 0.075 + 0.25 * np.sqrt(2) / 2 + 1e-6


def test_semantics_rejects_tilted_pose(world):
    T = world.local_from_global(world.true_pose(START_US))
    tilt = np.array([[1, 0, 0], [0, np.cos(0.01), -np.sin(0.01)], [0, np.sin(0.01), np.cos(0.01)]])
    T[:3, :3] = T[:3, :3] @ tilt
    with pytest.raises(ValueError, match="upright"):
        semantic_truth(world, 0.0, T)


def test_lidar_returns_lie_on_world_surfaces(world, frame):
    t_us, T, truth = frame
    sweep = sweep_at(world, t_us, T)
    t = float(world.seconds(t_us))
    tris = np.concatenate([world.static_mesh().triangles, world.agent_mesh(t).triangles])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(tris.reshape(-1, 3).astype(np.float32)),
                        o3d.core.Tensor(np.arange(len(tris) * 3, dtype=np.uint32).reshape(-1, 3)))
    cloud = sweep.cloud()  # "lidar" frame -> ego via the extrinsic -> local via the TRUE pose
    T_local = world.local_from_global(T) @ T_EGO_FROM_LIDAR
    pts = cloud.xyz @ T_local[:3, :3].T + T_local[:3, 3]
    dist = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    sigma = world.options.range_noise
    assert len(pts) > 30_000
    assert np.quantile(dist, 0.99) < 3.5 * sigma and np.max(dist) < 6 * sigma + 1e-3
    # every return's voxel is observed and the mask is far from empty
    idx, inside = GRID.point_to_index(sweep.hits)
    assert truth["mask_lidar"][tuple(idx[inside].T)].all()
    assert truth["mask_lidar"].sum() > 200_000


@pytest.mark.parametrize("seed", [0, 1, 6])
def test_ego_route_stays_on_the_road_and_turns(seed):
    w = build_world(get_preset("small"), SynthOptions(), seed=seed, log_index=0, duration=10.0, start_us=START_US)
    driven = w.ego.path.xy[w.ego.path.s <= w.ego.motion.s[-1]]
    half_width = 2.297 / 2
    assert shapely.distance(w.net.walkways, shapely.points(driven)).min() > half_width + 0.3
    state = w.ego_state(np.arange(0.0, 10.0, 0.05))
    assert np.allclose(state["T_local_from_ego"][:, 2, 3], SynthOptions().axle_height_m)  # TRUE rear axle above the road
    speed = state["velocity"][:, 0]
    assert speed.min() < 0.05 and speed.max() > 4.0  # stops at the intersection, then moves on
    yaw = np.unwrap(np.arctan2(state["T_local_from_ego"][:, 1, 0], state["T_local_from_ego"][:, 0, 0]))
    if w.ego.turns[0] != "straight":
        assert abs(yaw[-1] - yaw[0]) > np.radians(20)
