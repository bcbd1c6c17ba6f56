"""points_in_boxes and split_frame against analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
from fbsa_world import SENSOR_EGO, as_cloud, boxes_in_ego, make_sequence

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.aggregate import aggregate_objects
from nuplan_occ.evaluation.step_metrics import moving_leak_fraction
from nuplan_occ.aggregation.split import ego_footprint_boxes, points_in_boxes, split_frame
from nuplan_occ.geometry import make_transform, transform_points, yaw_matrix
from nuplan_occ.io.types import Boxes


def _random_boxes(rng: np.random.Generator, k: int, offset: np.ndarray, spread: float = 20.0) -> Boxes:
    centers = offset + rng.uniform(-spread, spread, (k, 3))
    sizes = rng.uniform(0.3, 6.0, (k, 3))
    yaws = rng.uniform(-np.pi, np.pi, k)
    tokens = [f"t{i}" for i in range(k)]
    return Boxes("global", centers, sizes, yaws, np.zeros((k, 3)), ["vehicle"] * k, tokens, tokens)


def _to_frame(boxes: Boxes, local: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Points given in box coordinates local (n, 3) of boxes[which] -> boxes.frame."""
    out = np.empty_like(local)
    for k in np.unique(which):
        T = make_transform(yaw_matrix(boxes.yaws[k]), boxes.centers[k])
        out[which == k] = transform_points(T, local[which == k])
    return out


@pytest.mark.parametrize("scale", [1.0, 1.1])
@pytest.mark.parametrize("offset", [np.zeros(3), np.array([664000.0, 3997000.0, 10.0])])
def test_points_in_boxes_faces_of_rotated_boxes(scale, offset):
    rng = np.random.default_rng(3)
    boxes = _random_boxes(rng, 12, offset)
    boxes.centers[:, 0] += np.arange(12) * 60.0  # far apart: no overlaps in this test
    which = rng.integers(0, 12, 3000)
    half = boxes.sizes[which] / 2 * scale
    inner = rng.uniform(-1, 1, (3000, 3)) * half
    axis = rng.integers(0, 3, 3000)
    sign = rng.choice([-1.0, 1.0], 3000)
    rows = np.arange(3000)
    on_face, just_in, just_out = inner.copy(), inner.copy(), inner.copy()
    on_face[rows, axis] = sign * half[rows, axis]
    just_in[rows, axis] = sign * (half[rows, axis] - 1e-3)
    just_out[rows, axis] = sign * (half[rows, axis] + 1e-3)
    for local, expect in ((on_face, which), (just_in, which), (just_out, np.full(3000, -1))):
        got = points_in_boxes(_to_frame(boxes, local, which), boxes, scale)
        np.testing.assert_array_equal(got, expect)


def test_points_in_boxes_matches_brute_force_with_overlaps():
    rng = np.random.default_rng(4)
    boxes = _random_boxes(rng, 40, np.zeros(3), spread=6.0)
    pts = rng.uniform(-10, 10, (20000, 3))
    expect, hits = np.full(len(pts), -1), np.zeros(len(pts), int)
    for k in range(len(boxes) - 1, -1, -1):  # lowest index wins
        local = (pts - boxes.centers[k]) @ yaw_matrix(boxes.yaws[k])
        inside = np.all(np.abs(local) <= boxes.sizes[k] / 2, axis=1)
        expect[inside] = k
        hits += inside
    got = points_in_boxes(pts, boxes)
    assert (expect >= 0).sum() > 3000 and (hits > 1).sum() > 300
    np.testing.assert_array_equal(got, expect)
    assert np.all(points_in_boxes(pts, Boxes.empty("global")) == -1)
    with pytest.raises(PointInputError):
        points_in_boxes(pts[:, :2], boxes)


@pytest.fixture(scope="module")
def seq():
    return make_sequence(10, seed=2)


def test_split_keeps_moving_objects_out_of_the_background(seq):
    car, ped = seq.world.car_id, seq.world.ped_id
    roof = np.random.default_rng(0).uniform([0.0, -0.9, 1.5], [3.0, 0.9, 1.8], (25, 3))  # returns off the ego roof
    splits, boxes_all, bg_ids = [], [], []
    for T, t, pts, ids in zip(seq.truth, seq.times, seq.clouds, seq.instance_ids):
        boxes = boxes_in_ego(seq.world, T, t)
        split = split_frame(as_cloud(np.vstack([pts, roof]), np.r_[ids, np.full(25, -5)]), boxes, SENSOR_EGO)
        splits.append(split)
        boxes_all.append(boxes)
        bg_ids.append(split.background.intensity.astype(int))
        assert split.n_ego == 25 and not np.any(bg_ids[-1] == -5)
        assert split.background.frame == "ego"
    all_ids = np.concatenate(seq.instance_ids)
    assert (all_ids == car).sum() > 50 and (all_ids == ped).sum() > 50
    assert moving_leak_fraction(np.concatenate(bg_ids), all_ids, [car, ped]) == 0.0
    assert sum(s.n_shell for s in splits) > 0

    objects = aggregate_objects([s.track_points() for s in splits], boxes_all)
    assert objects["car"].rigid and not objects["ped"].rigid
    np.testing.assert_allclose(objects["car"].size, seq.world.car_size)
    # In the box frame the moving car's points of all frames lie on the true box surface (the returns that
    # range noise pushed just outside the box went to the shell, not to the background).
    local, half = objects["car"].points, seq.world.car_size / 2
    assert len(local) >= 0.3 * (all_ids == car).sum()
    assert np.all(np.abs(local) <= half + 1e-6)
    gap_to_surface = np.min(half - np.abs(local), axis=1)
    assert np.percentile(gap_to_surface, 95) < 0.03
    # The sensor origin, moved into the box frame, is where the ray came from: points are seen from outside.
    assert np.all(np.linalg.norm(objects["car"].sensor_origins, axis=1) > np.linalg.norm(half))
    ped_pts, _ = objects["ped"].points_for_frame(5, window=1)
    assert set(objects["ped"].frame_ids[np.isin(objects["ped"].frame_ids, [4, 5, 6])]) <= {4, 5, 6}
    assert len(ped_pts) == np.isin(objects["ped"].frame_ids, [4, 5, 6]).sum()
    assert len(objects["car"].points_for_frame(5, window=1)[0]) == len(objects["car"].points)


def test_split_rejects_wrong_frames(seq):
    boxes = boxes_in_ego(seq.world, seq.truth[0], 0.0)
    cloud = as_cloud(seq.clouds[0], seq.instance_ids[0])
    with pytest.raises(PointInputError):
        split_frame(cloud, boxes.transformed(seq.truth[0], "global"), SENSOR_EGO)
    with pytest.raises(PointInputError):
        split_frame(cloud, boxes, SENSOR_EGO[:2])
    assert len(ego_footprint_boxes(margin_m=0.3)) == 1


def test_outside_boxes_clears_a_grown_box_but_keeps_the_ground_under_it():
    from nuplan_occ.aggregation.split import outside_boxes

    boxes = Boxes("ego", np.array([[10.0, 0.0, 0.8]]), np.array([[4.0, 2.0, 1.6]]), np.array([np.pi / 2]),
                  np.zeros((1, 3)), ["vehicle"], ["t"], ["b"])
    points = np.array([
        [10.0, 0.0, 0.8],     # inside the box
        [11.1, 0.0, 0.8],     # 0.1 m beyond a side face (box turned 90 deg: width along x)
        [11.3, 0.0, 0.8],     # 0.3 m beyond: outside the 0.2 m clearance
        [10.0, 0.0, 1.7],     # 0.1 m above the top
        [10.0, 2.1, 0.05],    # ground under the box's end, 0.05 m above its bottom
        [10.0, 2.1, 0.15],    # 0.15 m above the bottom, inside the grown end
    ])
    keep = outside_boxes(points, boxes, pad_m=0.2, ground_keep_m=0.1)
    assert keep.tolist() == [False, False, True, False, True, False]
    assert outside_boxes(points, Boxes.empty("ego"), 0.2, 0.1).all()
