"""Track repairs on hand-made box sequences with known answers (nuplan_occ.tracks.track_repair)."""

from __future__ import annotations

import numpy as np

from nuplan_occ.io.types import Boxes
from nuplan_occ.tracks.track_repair import TrackRepairParams, empty_tracks, repair_tracks, voted_headings

TIMES = np.arange(40) * 0.05
OFF = TrackRepairParams(heading_window_s=0, link_max_gap_s=0, fill_max_gap_s=0, duplicate_distance_m=0)


def _scene(tracks: dict[str, tuple[str, dict[int, tuple[np.ndarray, float]]]]) -> list[Boxes]:
    """Sweeps' boxes from track -> (category, frame -> (centre, yaw)); size 4.5 x 1.9 x 1.6, velocity 5 m/s along x."""
    out = []
    for f in range(len(TIMES)):
        rows = [(token, category, *at[f]) for token, (category, at) in tracks.items() if f in at]
        out.append(Boxes("global", np.array([r[2] for r in rows]).reshape(-1, 3), np.tile([4.5, 1.9, 1.6], (len(rows), 1)),
                         np.array([r[3] for r in rows], np.float64), np.tile([5.0, 0.0, 0.0], (len(rows), 1)),
                         [r[1] for r in rows], [r[0] for r in rows], [f"{r[0]}-{f}" for r in rows]))
    return out


def _moving(frames) -> dict[int, tuple[np.ndarray, float]]:
    return {f: (np.array([5.0 * TIMES[f], 0.0, 0.8]), 0.0) for f in frames}


def _of(boxes: list[Boxes], token: str) -> dict[int, tuple]:
    return {f: (b.centers[b.track_tokens.index(token)], b.yaws[b.track_tokens.index(token)])
            for f, b in enumerate(boxes) if token in b.track_tokens}


def test_voted_headings_follow_the_travel_of_a_turning_track_and_the_vote_of_a_parked_one():
    yaws = np.linspace(0.0, np.pi / 2, 40)  # a quarter turn over 2 s along a circle of 10 m radius
    centers = np.column_stack([10 * np.sin(yaws), 10 * (1 - np.cos(yaws)), np.zeros(40)])
    flipped = yaws.copy()
    flipped[[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 20, 21, 33]] += np.pi  # 13 of 40, the first 10 in a row
    assert np.allclose(np.cos(voted_headings(flipped, TIMES, 0.5, centers) - yaws), 1.0)
    parked = np.full(40, 0.3)
    parked[:15] += np.pi
    assert np.allclose(voted_headings(parked, TIMES, 0.5, np.zeros((40, 3))), 0.3)


def test_flipped_boxes_are_turned_back():
    at = _moving(range(40))
    for f in range(10, 20):
        at[f] = (at[f][0], np.pi)
    repaired, log = repair_tracks(_scene({"a": ("vehicle", at)}), TIMES, TrackRepairParams())
    assert log.flipped == {"a": 10}
    assert np.allclose([y for _, y in _of(repaired, "a").values()], 0.0)


def test_a_gap_is_filled_by_interpolation_and_a_long_one_is_not():
    scene = _scene({"a": ("vehicle", _moving([*range(0, 10), *range(20, 40)])),
                    "b": ("vehicle", {f: (np.array([0.0, 10.0, 0.8]), 0.0) for f in [0, 39]})})
    repaired, log = repair_tracks(scene, TIMES, TrackRepairParams(fill_max_gap_s=0.6))
    boxes = _of(repaired, "a")
    assert sorted(boxes) == list(range(40)) and log.filled == {"a": 10}
    for f in range(10, 20):
        assert np.allclose(boxes[f][0], [5.0 * TIMES[f], 0.0, 0.8])
    assert sorted(_of(repaired, "b")) == [0, 39]  # 1.95 s apart: not filled
    assert repaired[12].tokens[repaired[12].track_tokens.index("a")] == "a@12"


def test_an_id_switch_is_linked_and_a_distant_start_is_not():
    scene = _scene({"a": ("vehicle", _moving(range(0, 20))), "b": ("vehicle", _moving(range(23, 40))),
                    "c": ("vehicle", {f: (np.array([5.0 * TIMES[f], 6.0, 0.8]), 0.0) for f in range(25, 40)})})
    repaired, log = repair_tracks(scene, TIMES, TrackRepairParams())
    assert log.linked == {"b": "a"}
    assert sorted(_of(repaired, "a")) == list(range(40))  # linked, then its gap filled
    assert sorted(_of(repaired, "c")) == list(range(25, 40))


def test_a_duplicate_track_is_dropped_and_a_neighbour_is_kept():
    twin = {f: (np.array([5.0 * TIMES[f], 0.4, 0.8]), 0.0) for f in range(10, 30)}
    beside = {f: (np.array([5.0 * TIMES[f], 2.5, 0.8]), 0.0) for f in range(10, 30)}
    scene = _scene({"a": ("vehicle", _moving(range(40))), "twin": ("vehicle", twin), "beside": ("vehicle", beside)})
    repaired, log = repair_tracks(scene, TIMES, TrackRepairParams())
    assert log.duplicates == {"twin": "a"}
    assert not _of(repaired, "twin") and sorted(_of(repaired, "beside")) == list(range(10, 30))


def test_repairs_off_leave_the_boxes():
    at = _moving([*range(0, 10), *range(20, 40)])
    at[5] = (at[5][0], np.pi)
    scene = _scene({"a": ("vehicle", at)})
    repaired, log = repair_tracks(scene, TIMES, OFF)
    assert not (log.flipped or log.filled or log.linked or log.duplicates)
    for a, b in zip(scene, repaired):
        assert a.track_tokens == b.track_tokens and np.array_equal(a.centers, b.centers) and np.array_equal(a.yaws, b.yaws)


def test_empty_tracks_are_those_holding_only_ground_points():
    ground = np.array([[0.0, 0.0, -0.78], [1.0, 0.5, -0.75]])  # a 1.6 m box's bottom at z = -0.8
    body = np.array([[0.5, 0.2, 0.1]] * 12)
    views = {"fp": [ground, ground], "car": [ground, body], "cone": [np.array([[0.0, 0.0, 0.3]] * 3)]}
    assert empty_tracks(views, {"fp": 1.6, "car": 1.6, "cone": 0.7}, 0.3, 10) == {"fp", "cone"}
    assert empty_tracks(views, {"fp": 1.6, "car": 1.6, "cone": 0.7}, 0.3, 3) == {"fp"}


def test_robust_travel_ignores_box_noise_and_sees_a_slow_move():
    from nuplan_occ.tracks.scene_tracks import robust_travel

    rng = np.random.default_rng(2)
    parked = rng.normal(0.0, 0.15, (400, 2))  # the realistic profile's centre noise: single boxes stray 0.7 m
    assert np.max(np.linalg.norm(parked - parked[0], axis=1)) > 0.5 and robust_travel(parked) < 0.1
    creeping = parked + np.column_stack([np.linspace(0.0, 1.0, 400), np.zeros(400)])
    assert robust_travel(creeping) > 0.6
    assert robust_travel(np.zeros((1, 2))) == 0.0
