"""fbsa.box_snap: a small object's box moved onto its points, with the ground and a curb beside it."""

from __future__ import annotations

import numpy as np

from nuplan_occ.tracks.box_snap import BoxSnapParams, snap_shift


def cone_scene(offset: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Points in the frame of a 0.3 x 0.3 x 0.5 m box centred 0.25 m above the ground, around a cone
    whose true centre is at `offset` (x, y): its near-side surface, the road and a 0.15 m curb 0.3 m away."""
    ground_z = -0.25
    road = np.column_stack([rng.uniform(-1.2, 1.2, (3000, 2)), np.full(3000, ground_z) + rng.normal(0, 0.01, 3000)])
    curb = np.column_stack([rng.uniform(-1.2, 1.2, 400), offset[1] + 0.3 + rng.uniform(0, 0.05, 400),
                            ground_z + rng.uniform(0.0, 0.15, 400)])
    angle = rng.uniform(-np.pi / 2, np.pi / 2, 200)  # the side facing the sensor
    height = rng.uniform(0.05, 0.5, 200)
    radius = 0.15 * (1 - height / 0.55)
    cone = np.column_stack([offset[0] - radius * np.cos(angle), offset[1] + radius * np.sin(angle), ground_z + height])
    return np.vstack([road, curb, cone])


def test_the_box_moves_onto_the_cone_not_the_curb():
    rng = np.random.default_rng(0)
    size = np.array([0.3, 0.3, 0.5])
    for offset in (np.array([0.25, -0.2]), np.array([-0.3, 0.1]), np.array([0.0, 0.0])):
        shift = snap_shift(cone_scene(offset, rng), size)
        # the cone's points span its near half: the box centre lands within half its size of the true centre
        assert np.all(np.abs(shift - offset) <= 0.1), (offset, shift)


def test_no_object_points_no_shift():
    rng = np.random.default_rng(1)
    road = np.column_stack([rng.uniform(-1, 1, (2000, 2)), rng.normal(-0.25, 0.01, 2000)])
    assert np.array_equal(snap_shift(road, np.array([0.3, 0.3, 0.5])), [0.0, 0.0])
    assert np.array_equal(snap_shift(np.zeros((0, 3)), np.array([0.3, 0.3, 0.5])), [0.0, 0.0])


def test_shift_is_bounded_by_the_radius():
    rng = np.random.default_rng(2)
    far = cone_scene(np.array([0.7, 0.0]), rng)  # reachable only in part: the box moves as far as allowed
    shift = snap_shift(far, np.array([0.3, 0.3, 0.5]), BoxSnapParams(radius_m=0.5))
    assert 0.4 <= np.linalg.norm(shift) <= 0.5 + 1e-9 and shift[0] > 0.4


def test_a_canopy_above_is_not_taken_for_the_ground():
    """A tree crown 3 m up over one side of a box holding its cone: more canopy points than ground points
    near the box must not make the canopy the 'ground' and pull the box under the crown."""
    rng = np.random.default_rng(3)
    scene = cone_scene(np.array([0.0, 0.0]), rng)
    canopy = np.column_stack([rng.uniform(-1.2, 1.2, 12000), rng.uniform(0.3, 1.2, 12000), rng.uniform(2.8, 3.4, 12000)])
    shift = snap_shift(np.vstack([scene, canopy]), np.array([0.3, 0.3, 0.5]))
    assert np.all(np.abs(shift) <= 0.1), shift
    unbanded = snap_shift(np.vstack([scene, canopy]), np.array([0.3, 0.3, 0.5]), BoxSnapParams(z_band_m=10.0))
    assert np.abs(unbanded).max() > 0.2  # without the height band the crown wins
