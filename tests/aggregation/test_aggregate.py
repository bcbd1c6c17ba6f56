"""aggregate_background / aggregate_objects against hand-made frames."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.aggregate import BackgroundAggregate, aggregate_background, aggregate_objects, within_boxes, without_outliers
from nuplan_occ.aggregation.split import FrameSplit
from nuplan_occ.geometry import invert_transform, make_transform, rotation_from_euler, transform_points
from nuplan_occ.io.types import Boxes, PointCloud


def _poses(n: int) -> np.ndarray:
    return np.stack([make_transform(rotation_from_euler(0.01 * i, -0.02 * i, 0.3 * i), [664000.0 + 5 * i, 3997000.0, 12.0])
                     for i in range(n)])


def test_background_lands_in_the_scene_frame():
    rng = np.random.default_rng(0)
    world = rng.uniform(-20, 20, (300, 3)) + [664000.0, 3997000.0, 12.0]  # global points seen by every frame
    poses = _poses(3)
    clouds = [transform_points(invert_transform(T), world) for T in poses]
    origins = np.array([[1.3, 0.0, 1.9], [1.3, 0.1, 1.9], [1.2, 0.0, 2.0]])
    agg = aggregate_background(clouds, origins, poses)
    np.testing.assert_allclose(agg.T_global_from_scene, poses[0])
    np.testing.assert_allclose(transform_points(poses[0], agg.points), np.vstack([world] * 3), atol=1e-6)
    np.testing.assert_array_equal(agg.frame_ids, np.repeat(np.arange(3), 300).astype(np.int32))
    expected_origin = transform_points(invert_transform(poses[0]) @ poses[2], origins[2][None])[0]
    np.testing.assert_allclose(agg.frame_origins[agg.frame_ids[agg.frame_ids == 2]], np.tile(expected_origin, (300, 1)), atol=1e-9)

    down = aggregate_background(clouds, origins, poses, T_global_from_scene=poses[1], voxel_downsample_m=0.5)
    keys = np.floor(down.points / 0.5).astype(np.int64)
    assert len(np.unique(keys, axis=0)) == len(down.points) <= 300
    assert np.all(down.frame_ids == 0)  # the earliest frame's point is kept in every voxel
    back = transform_points(poses[1], down.points)
    nearest = np.min(np.linalg.norm(back[:, None] - world[None], axis=2), axis=1)
    assert np.all(nearest < 1e-6)  # kept points are input points, not averages
    with pytest.raises(PointInputError):
        aggregate_background(clouds, origins[:2], poses)


def _split(points: dict[str, np.ndarray]) -> FrameSplit:
    empty = PointCloud(np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.int16), np.zeros(0, np.int8), "ego")
    return FrameSplit(empty, points, {t: np.zeros_like(p) for t, p in points.items()}, 0, 0)


def _boxes(tokens: list[str], categories: list[str], lengths: list[float]) -> Boxes:
    k = len(tokens)
    sizes = np.array([[length, 2.0, 1.5] for length in lengths]).reshape(k, 3)
    return Boxes("ego", np.zeros((k, 3)), sizes, np.zeros(k), np.zeros((k, 3)), categories, tokens, tokens)


def test_background_crop_keeps_points_inside_some_frame_box():
    rng = np.random.default_rng(1)
    world = rng.uniform(-40, 40, (2000, 3)) + [664000.0, 3997000.0, 12.0]
    poses = _poses(3)
    clouds = [transform_points(invert_transform(T), world) for T in poses]
    origins = np.zeros((3, 3))
    lower, upper = np.array([-10.0, -5.0, -2.0]), np.array([10.0, 5.0, 3.0])
    crop_poses = poses[[0, 2]]
    agg = aggregate_background(clouds, origins, poses, crop=(crop_poses, lower, upper))
    inside = np.zeros(len(world), dtype=bool)  # the truth, point by point and frame by frame
    for T in crop_poses:
        for j, local in enumerate(transform_points(invert_transform(T), world)):
            inside[j] |= bool(np.all(local >= lower) and np.all(local < upper))
    assert 0 < inside.sum() < len(world)
    np.testing.assert_array_equal(within_boxes(world, np.stack([invert_transform(T) for T in crop_poses]), lower, upper),
                                  inside)
    np.testing.assert_allclose(transform_points(poses[0], agg.points), np.vstack([world[inside]] * 3), atol=1e-6)
    assert np.array_equal(agg.frame_ids, np.repeat(np.arange(3), inside.sum()).astype(np.int32))


def test_objects_keep_their_frames_and_rigidity():
    splits = [_split({"a": np.ones((2, 3)), "p": np.full((3, 3), i)}) for i in range(5)]
    boxes = [_boxes(["a", "p", "z"], ["vehicle", "pedestrian", "barrier"], [4.0 + 0.1 * i, 0.6, 1.0]) for i in range(5)]
    objects = aggregate_objects([s.track_points() for s in splits], boxes)
    assert set(objects) == {"a", "p", "z"}
    a, p, z = objects["a"], objects["p"], objects["z"]
    assert a.rigid and not p.rigid and z.rigid and a.category == "vehicle"
    np.testing.assert_allclose(a.size, [4.2, 2.0, 1.5])
    assert len(a.points) == 10 and len(z.points) == 0 and z.frame_ids.dtype == np.int32
    pts, origins = p.points_for_frame(2, window=1)
    np.testing.assert_array_equal(np.unique(pts[:, 0]), [1.0, 2.0, 3.0])
    assert len(origins) == 9 and len(a.points_for_frame(0, window=0)[0]) == 10
    with pytest.raises(PointInputError):
        aggregate_objects([s.track_points() for s in splits], boxes[:4])
    with pytest.raises(PointInputError):
        aggregate_objects([_split({"ghost": np.ones((1, 3))}).track_points()], [_boxes([], [], [])])


def test_outliers_of_the_aggregate_are_removed_against_each_points_own_sensor():
    """Two sweeps' ground returns, spaced in proportion to their range as a LiDAR's are, 20 m apart, plus 40
    floaters 1-3 m above the ground: "range" removes every floater and almost no ground; "none" keeps all."""
    rng = np.random.default_rng(3)
    sensors = np.array([[-10.0, 0.0, 1.8], [10.0, 0.0, 1.8]])
    ranges = 2.0 * 1.01 ** np.arange(200)  # 2 m to 14.6 m, rings 1 % of their range apart
    azimuths = np.radians(np.arange(0.0, 360.0, 0.6))
    r, a = (g.ravel() for g in np.meshgrid(ranges, azimuths, indexing="ij"))
    ring = np.c_[r * np.cos(a), r * np.sin(a), rng.normal(0.0, 0.003, len(r))]
    ground = np.vstack([ring + [sensor[0], sensor[1], 0.0] for sensor in sensors])
    floaters = np.c_[rng.uniform(-20, 20, 40), rng.uniform(-12, 12, 40), rng.uniform(1.0, 3.0, 40)]
    points = np.vstack([ground, floaters])
    frame_ids = np.r_[np.repeat(np.arange(2, dtype=np.int32), len(ring)), rng.integers(0, 2, 40).astype(np.int32)]
    aggregate = BackgroundAggregate(points, frame_ids, sensors, np.eye(4))
    kept, removed = without_outliers(aggregate, {"method": "range", "nb_neighbors": 8, "std_ratio": 2.0})
    assert (kept.points[:, 2] < 0.5).all()  # no floater left
    assert len(kept.points) >= 0.995 * len(ground)
    survivors = np.flatnonzero(np.isin(points[:, 0], kept.points[:, 0]) & (points[:, 2] < 0.5))
    np.testing.assert_array_equal(kept.frame_ids, frame_ids[survivors])
    np.testing.assert_array_equal(removed, np.bincount(frame_ids, minlength=2) - np.bincount(kept.frame_ids, minlength=2))
    unchanged, none_removed = without_outliers(aggregate, {"method": "none"})
    assert unchanged is aggregate and none_removed.tolist() == [0, 0]
