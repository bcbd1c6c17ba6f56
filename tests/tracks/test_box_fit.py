"""Boxes fitted to their track's points (nuplan_occ.tracks.box_fit), on exact synthetic point sets."""

from __future__ import annotations

import numpy as np

from nuplan_occ.io.types import Boxes
from nuplan_occ.tracks.box_fit import BoxFitParams, fitted_boxes, fitted_extents, grown_extent, shrunk_extent


def _pedestrian(rng: np.random.Generator) -> np.ndarray:
    body = rng.uniform([-0.3, -0.3, -0.875], [0.3, 0.3, 0.875], (400, 3))  # a 0.6 x 0.6 x 1.75 m pedestrian
    ground = np.column_stack([rng.uniform(-0.6, 0.6, (200, 2)), np.full(200, -0.875)])
    return np.vstack([body, ground])


def test_a_small_box_grows_to_its_points_by_at_most_the_margin_and_a_fitting_one_stays():
    points = _pedestrian(np.random.default_rng(1))
    params = BoxFitParams(grow_margin_m=0.3, floor_clearance_m=0.1)
    grown = grown_extent(points, np.array([0.45, 0.45, 1.31]), params)
    assert np.allclose(2 * grown.half, [0.6, 0.6, 1.75], atol=0.03) and grown.z_shift == 0.0
    capped = grown_extent(points, np.array([0.45, 0.45, 1.31]), BoxFitParams(grow_margin_m=0.05, floor_clearance_m=0.1))
    assert np.allclose(2 * capped.half, [0.55, 0.55, 1.41])
    assert grown_extent(points, np.array([0.62, 0.62, 1.8]), params) is None


def _truck_surface(rng: np.random.Generator, sides: tuple[str, ...]) -> np.ndarray:
    """Returns on a 7.7 x 2.4 x 2.6 m truck standing on the road at z = 0, seen on `sides`, plus road around it."""
    n = 600
    faces = {
        "left": lambda: np.column_stack([rng.uniform(-3.85, 3.85, n), np.full(n, 1.2), rng.uniform(0.3, 2.6, n)]),
        "front": lambda: np.column_stack([np.full(n, 3.85), rng.uniform(-1.2, 1.2, n), rng.uniform(0.3, 2.6, n)]),
        "top": lambda: np.column_stack([rng.uniform(-3.85, 3.85, n), rng.uniform(-1.2, 1.2, n), np.full(n, 2.6)]),
    }
    road = np.column_stack([rng.uniform(-4.8, 4.8, (n, 2)), np.zeros(n)])
    return np.vstack([faces[s]() for s in sides] + [road])


def test_an_oversized_box_shrinks_to_its_truck_keeping_the_hidden_side_and_the_road_under_it():
    rng = np.random.default_rng(2)
    true_half = np.array([3.85, 1.2, 1.3])
    oversized = 2 * true_half * 1.25  # centred on the truck: its bottom 0.33 m under the road
    centre_z = 1.3  # the truck's centre above the road
    points = _truck_surface(rng, ("left", "front")) - [0.0, 0.0, centre_z]  # box frame
    params = BoxFitParams(pad_m=0.1, floor_clearance_m=0.3)
    fit = shrunk_extent(points, oversized, params)
    assert np.allclose(fit.half[:2], true_half[:2] + 0.1, atol=0.03)  # the unseen right side kept by symmetry
    bottom, top = fit.z_shift - fit.half[2], fit.z_shift + fit.half[2]
    assert abs(bottom - (-centre_z - 0.1)) < 0.03  # down to the road, less the pad: no longer under it
    assert abs(top - (2.6 - centre_z + 0.1)) < 0.03


def test_a_shrink_is_capped_a_fitting_box_stays_and_few_points_leave_a_box_alone():
    rng = np.random.default_rng(3)
    points = _truck_surface(rng, ("left", "front", "top")) - [0.0, 0.0, 1.3]
    capped = shrunk_extent(points, np.array([7.7, 2.4, 2.6]) * 2.0, BoxFitParams(max_shrink=0.25))
    assert np.allclose(capped.half[:2], [7.7 * 0.75, 2.4 * 0.75])
    assert shrunk_extent(points, np.array([7.9, 2.6, 2.8]), BoxFitParams(pad_m=0.1)) is None
    assert shrunk_extent(points[:5], np.array([10.0, 3.0, 3.3]), BoxFitParams()) is None
    assert shrunk_extent(points, np.array([10.0, 3.0, 3.3]), BoxFitParams(max_shrink=0.0)) is None


def test_fitted_boxes_resize_every_sweep_of_a_track_and_raise_its_centre():
    rng = np.random.default_rng(4)
    truck = _truck_surface(rng, ("left", "front", "top"))
    oversized = np.array([9.6, 3.0, 3.25])
    center = np.array([10.0, 0.0, 1.3])  # ego frame; the road at z = 0

    def boxes(k: int) -> Boxes:
        return Boxes("ego", np.array([center]), np.array([oversized]), np.zeros(1), np.zeros((1, 3)), ["vehicle"],
                     ["truck"], [f"b{k}"])

    sweeps = {0: boxes(0), 1: boxes(1)}
    extents = fitted_extents(sweeps, lambda i: truck + center - [0.0, 0.0, 1.3], np.zeros(3), BoxFitParams())
    fitted = fitted_boxes(sweeps, extents)
    for b in fitted.values():
        assert np.allclose(b.sizes[0], [7.9, 2.6, 2.8], atol=0.05)
        assert abs(b.centers[0, 2] - b.sizes[0, 2] / 2 - (-0.1)) < 0.05  # bottom at the road less the pad
    assert fitted_extents(sweeps, lambda i: truck, np.zeros(3), BoxFitParams(shrink_categories=())) == {}


def test_a_box_too_low_for_its_truck_raises_its_top_to_the_roof_by_at_most_the_cap():
    """An auto-labelled box 0.3 m too short, standing on the road: the roof's returns lie above it. The top
    rises to them (the points decide the shape), by at most raise_max_m; the bottom stays, and so does each
    sweep's own length and width (the sides were not fitted)."""
    rng = np.random.default_rng(6)
    truck = _truck_surface(rng, ("left", "front", "top"))  # the road at z = 0, the roof at 2.6
    center = np.array([10.0, 0.0, 1.15])  # ego frame: bottom on the road, top 0.3 m under the roof

    def boxes(k: int) -> Boxes:
        low = np.array([7.7 + 0.04 * k, 2.4, 2.3])
        return Boxes("ego", np.array([center]), np.array([low]), np.zeros(1), np.zeros((1, 3)), ["vehicle"],
                     ["truck"], [f"b{k}"])

    sweeps = {0: boxes(0), 1: boxes(1)}
    for cap, top in ((0.5, 2.6 + 0.1), (0.2, 2.3 + 0.2)):
        fitted = fitted_boxes(sweeps, fitted_extents(sweeps, lambda i: truck + [10.0, 0.0, 0.0], np.zeros(3),
                                                     BoxFitParams(raise_max_m=cap)))
        for k, b in fitted.items():
            assert abs(b.centers[0, 2] + b.sizes[0, 2] / 2 - top) < 0.02  # the roof plus the pad, or the cap
            assert abs(b.centers[0, 2] - b.sizes[0, 2] / 2) < 1e-9  # the bottom stays on the road
            assert np.allclose(b.sizes[0, :2], [7.7 + 0.04 * k, 2.4])
    assert fitted_extents(sweeps, lambda i: truck + [10.0, 0.0, 0.0], np.zeros(3), BoxFitParams(raise_max_m=0.0)) == {}


def test_a_truck_seen_above_its_lower_part_keeps_it():
    """A fitting truck box whose lower 1.5 m few returns saw (its upper part seen over parked cars): the bottom
    rises by at most the floor band (0.3 m), not to the lowest returns, so the truck keeps its lower part."""
    rng = np.random.default_rng(4)
    points = _truck_surface(rng, ("left", "front", "top")) - [0.0, 0.0, 1.3]  # box frame, bottom at -1.3
    seen = points[points[:, 2] > -1.3 + 1.5]
    fit = shrunk_extent(seen, np.array([7.7, 2.4, 2.6]), BoxFitParams(pad_m=0.1, floor_clearance_m=0.3))
    bottom = fit.z_shift - fit.half[2]
    assert abs(bottom - (-1.3 + 0.3)) < 1e-9


def test_a_truck_whose_full_length_few_sweeps_saw_keeps_its_length():
    """A fitting 7 m truck box: 20000 returns on its cab (the middle 3 m, seen over the cars around it) and 600 on its
    full-length body below (3 %: the few sweeps that saw it). The shrink's 0.999 quantile keeps the length; the
    0.99 of a grow would cut it to the cap."""
    rng = np.random.default_rng(5)
    cab = rng.uniform([-1.5, -1.2, 0.0], [1.5, 1.2, 1.5], (20000, 3))
    body = rng.uniform([-3.5, -1.2, -1.2], [3.5, 1.2, 0.0], (600, 3))
    size = np.array([7.0, 2.4, 3.0])
    fit = shrunk_extent(np.vstack([cab, body]), size, BoxFitParams(pad_m=0.1))
    assert fit is None or fit.half[0] >= 3.4  # within 0.1 m of the true half length
    cut = shrunk_extent(np.vstack([cab, body]), size, BoxFitParams(pad_m=0.1, shrink_quantile=0.99))
    assert abs(cut.half[0] - 3.5 * 0.75) < 1e-9
