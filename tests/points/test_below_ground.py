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


def _street_with_a_hidden_patch(rng: np.random.Generator, depth: tuple[float, float], from_x: float = 29.0,
                                count: int = 40):
    """(sensor origin, road, kerb, ghosts): a road seen from a sensor 2 m up at the origin holds a patch never seen
    (x 26-46 m, y 4-10 m: behind parked cars); ghosts of road returns 8-20 m ahead lie `depth` m under the road,
    further along their rays (as the synth's multipath ghosts), those landing inside the patch beyond from_x kept; a
    kerb stone stands at the patch's edge."""
    sensor = np.array([0.0, 0.0, 2.0])
    road = np.column_stack([rng.uniform(2, 60, 60000), rng.uniform(-2, 10, 60000), rng.normal(0.0, 0.02, 60000)])
    road = road[~((road[:, 0] > 26) & (road[:, 0] < 46) & (road[:, 1] > 4))]
    hit = np.column_stack([rng.uniform(8, 20, 40000), rng.uniform(2, 5, 40000), np.zeros(40000)])
    ray = hit - sensor
    ghosts = hit + ray * (rng.uniform(*depth, len(hit)) / -ray[:, 2])[:, None]
    ghosts = ghosts[(ghosts[:, 0] > from_x) & (ghosts[:, 0] < 43) & (ghosts[:, 1] > 7)]
    ghosts = ghosts[rng.permutation(len(ghosts))[:count]]  # sparse, as ghosts of one sweep are: 0.2 % of the returns
    kerb = np.column_stack([np.full(300, 26.2), rng.uniform(4, 10, 300), rng.uniform(0.0, 0.15, 300)])
    return sensor, road, kerb, ghosts


def test_ghosts_where_no_ground_was_seen_are_found_against_the_typical_ground():
    """Ghosts 1.1-3 m deep in the hidden patch have no ground of their own (or a sparse one of their own making):
    the typical ground around finds them, with no origin needed. With that test off they stay."""
    sensor, road, kerb, ghosts = _street_with_a_hidden_patch(np.random.default_rng(1), (1.1, 3.0))
    points = np.concatenate([road, kerb, ghosts])
    assert len(ghosts) >= 30
    found = below_ground(points, depth_m=0.5)
    assert found[-len(ghosts):].all() and not found[:-len(ghosts)].any()
    assert not below_ground(points, depth_m=0.5, sparse_depth_m=np.inf)[-len(ghosts):].any()


def test_shallow_ghosts_in_the_hidden_patch_are_found_by_their_rays():
    """Ghosts 0.6-1 m deep in the patch are above the typical-ground margin; their rays ran under the road on the
    way, and most are found so; a miss is a ray that is that deep under known ground only between two of the sampled
    distances, or under ground that ghosts near the patch's edge pulled down."""
    sensor, road, kerb, ghosts = _street_with_a_hidden_patch(np.random.default_rng(2), (0.6, 1.0), from_x=27.0)
    points = np.concatenate([road, kerb, ghosts])
    assert len(ghosts) >= 30
    assert not below_ground(points, depth_m=0.5)[-len(ghosts):].any()
    with_rays = below_ground(points, depth_m=0.5, origins=sensor)
    assert with_rays[-len(ghosts):].mean() >= 0.6
    assert not with_rays[:-len(ghosts)].any()


def test_ghosts_piled_up_over_many_sweeps_are_found_by_their_rays():
    """Many sweeps' ghosts pile up in the hidden patch (1.1-3 m deep, ~40 per square metre): dense cells, their own
    low ground, which the typical-ground test leaves alone (and the typical ground is theirs where they fill most of
    the 15 m around). They are ground-like and their rays ran under the road or the kerb: found, but for a few at
    the patch's far end whose rays rise out of the depth margin just as they leave the patch; no road or kerb point
    with them. A second pass, over the points the first kept, finds more than one pass does."""
    sensor, road, kerb, ghosts = _street_with_a_hidden_patch(np.random.default_rng(4), (1.1, 3.0), count=1600)
    points = np.concatenate([road, kerb, ghosts])
    assert len(ghosts) == 1600
    found = below_ground(points, depth_m=0.5, origins=sensor)
    assert found[-len(ghosts):].mean() >= 0.95 and not found[:-len(ghosts)].any()
    one_pass = below_ground(points, depth_m=0.5, origins=sensor, passes=1)
    assert one_pass[-len(ghosts):].sum() < found[-len(ghosts):].sum()


def test_a_cutting_seen_densely_keeps_its_low_ground():
    """A 10 m wide cutting 2.5 m below the street, seen densely: its ground is real, dense cells are never tested
    against the typical ground, and its rays come straight down into it."""
    rng = np.random.default_rng(3)
    street = np.column_stack([rng.uniform(0, 60, 60000), rng.uniform(-20, 20, 60000), rng.normal(0.0, 0.02, 60000)])
    inside = (np.abs(street[:, 1]) < 5)
    street[inside, 2] -= 2.5
    origins = np.column_stack([street[:, 0] - 5.0, np.zeros(len(street)), np.full(len(street), 2.0)])
    origins[inside, 2] = -0.5  # the sensor drives in the cutting when it sees its floor
    assert not below_ground(street, depth_m=0.5, origins=origins)[inside].any()
