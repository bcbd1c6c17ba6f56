"""Points under the ground (nuplan_occ.points.below_ground) on a hand-made street with known ghosts."""

from __future__ import annotations

import numpy as np

from nuplan_occ.points.below_ground import below_ground


def test_ghosts_under_a_road_beside_a_wall_are_found_and_the_wall_kept():
    rng = np.random.default_rng(0)
    road = np.column_stack([rng.uniform(0, 20, 20000), rng.uniform(0, 10, 20000), rng.normal(0.0, 0.02, 20000)])
    wall = np.column_stack([rng.uniform(0, 20, 5000), rng.uniform(10.0, 10.2, 5000), rng.uniform(0.0, 12.0, 5000)])
    ghosts = np.column_stack([rng.uniform(0, 20, 60), rng.uniform(0, 12, 60), -rng.uniform(1.0, 3.0, 60)])
    shallow = np.column_stack([rng.uniform(0, 20, 50), rng.uniform(0, 10, 50), np.full(50, -0.3)])  # within 0.5 m
    points = np.concatenate([road, wall, ghosts, shallow])
    below = below_ground(points, depth_m=0.5)
    assert below[len(road) + len(wall):len(road) + len(wall) + 60].all()
    assert not below[:len(road) + len(wall)].any() and not below[-50:].any()


def test_no_points_and_unknown_ground():
    assert below_ground(np.zeros((0, 3))).shape == (0,)
    few = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -2.0]])  # fewer than min_cell_points: ground unknown
    assert not below_ground(few).any()
