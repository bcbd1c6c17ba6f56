"""seen_through on the analytic street (tests/fbsa/fbsa_world.py): the car driving the other way and the walking
pedestrian leave points along their paths when all sweeps are aggregated; free-space evidence removes them and
keeps the ground, the buildings, the poles and the parked cars."""

from __future__ import annotations

import numpy as np
import pytest

from fbsa_world import GROUND, SENSOR_EGO, make_sequence
from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.dynamic import dilate, height_above_ground, seen_through
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.rays.visibility import lidar_observation_bits


@pytest.fixture(scope="module")
def street():
    seq = make_sequence(n_frames=20)
    T = np.stack([invert_transform(seq.truth[0]) @ T_f for T_f in seq.truth])  # scene = first ego frame
    points = np.vstack([transform_points(T_f, c) for T_f, c in zip(T, seq.clouds)])
    ids = np.concatenate(seq.instance_ids)
    remove = seen_through(points, [lidar_observation_bits(c, SENSOR_EGO) for c in seq.clouds], T)
    return seq, points, ids, remove


def test_movers_above_the_ground_are_removed(street):
    seq, points, ids, remove = street
    # the slow walker (1.2 m/s) stays within a voxel of its old returns for several sweeps, which then
    # count against removal: only part of its trail goes (measured 0.59), the car's (8 m/s) nearly all (0.99)
    for mover, share in ((seq.world.car_id, 0.9), (seq.world.ped_id, 0.4)):
        above = (ids == mover) & (points[:, 2] > 0.5)
        assert above.sum() > 100
        assert remove[above].mean() > share, (mover, remove[above].mean())


def test_static_scene_and_ground_survive(street):
    seq, points, ids, remove = street
    static = ids < seq.world.car_id  # ground (-1) and every static box: buildings, poles, parked cars
    assert not remove[ids == GROUND].any()
    assert remove[static].mean() < 0.005, remove[static].mean()
    labels = np.array(seq.world.static_labels)
    for label in ("building", "pole", "parked"):
        members = np.isin(ids, np.flatnonzero(labels == label))
        assert remove[members].mean() < 0.01, (label, remove[members].mean())


def test_no_votes_no_removal():
    points = np.array([[5.1, 0.1, 1.1], [5.1, 0.1, 0.0]])
    T = np.eye(4)[None]
    ray = SENSOR_EGO + 2.0 * (points[0] - SENSOR_EGO)  # one sweep looks through the upper point: one vote
    observation = lidar_observation_bits(ray[None], SENSOR_EGO)
    assert not seen_through(points, [observation], T).any()
    assert seen_through(points, [observation], T, min_votes=1).tolist() == [True, False]
    with pytest.raises(PointInputError):
        seen_through(points, [observation], np.eye(4)[None].repeat(2, axis=0))
    with pytest.raises(PointInputError):
        seen_through(points, [(observation[0][:-1], observation[1])], T)


def test_helpers():
    pts = np.array([[0.2, 0.2, 1.0], [0.7, 0.1, 3.0], [1.5, 0.5, 2.0]])
    np.testing.assert_allclose(height_above_ground(pts, 1.0), [0.0, 2.0, 0.0])
    m = np.zeros((5, 5, 5), dtype=bool)
    m[0, 2, 4] = True
    d = dilate(m, 1)
    assert d.sum() == 2 * 3 * 2 and d[1, 3, 3] and not d[2, 2, 4]
