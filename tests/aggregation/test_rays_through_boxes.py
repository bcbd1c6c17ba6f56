"""nuplan_occ.aggregation.carve.rays_through_boxes: background rays crossing a box are kept, in its box frame, only for the listed tracks."""

import numpy as np

from nuplan_occ.io.types import Boxes
from nuplan_occ.aggregation.carve import rays_through_boxes


def boxes(tracks, centers, yaws):
    k = len(tracks)
    return Boxes("ego", np.asarray(centers, float), np.tile([2.0, 1.0, 1.0], (k, 1)), np.asarray(yaws, float),
                 np.zeros((k, 3)), ["czone_sign"] * k, list(tracks), list(tracks))


class Reads(list):
    """A list that records which elements were read."""

    def __init__(self, items):
        super().__init__(items)
        self.read = []

    def __getitem__(self, i):
        self.read.append(i)
        return super().__getitem__(i)


def test_only_listed_tracks_get_the_rays_crossing_their_box_in_their_box_frame():
    origin = np.zeros(3)
    # sweep 0: a sign at x = 10 turned by 90 degrees; one return behind it (crosses), one beside it (misses)
    sweep0 = np.array([[20.0, 0.0, 0.0], [20.0, 5.0, 0.0]])
    # sweep 1 boxes only an unlisted track: its points are never read
    sweep1 = np.array([[30.0, 0.0, 0.0]])
    backgrounds = Reads([sweep0, sweep1])
    found = rays_through_boxes(backgrounds,
                               [boxes(["sign", "car"], [[10.0, 0.0, 0.0], [10.0, 0.0, 0.0]], [np.pi / 2, 0.0]),
                                boxes(["car"], [[15.0, 0.0, 0.0]], [0.0])],
                               origin, {"sign"})
    assert set(found) == {"sign"} and backgrounds.read == [0]
    starts, ends = found["sign"]
    # box frame: x along the heading (ego +y), so the ray along ego +x runs along box -y, from y = 10 to y = -10
    assert np.allclose(starts, [[0.0, 10.0, 0.0]]) and np.allclose(ends, [[0.0, -10.0, 0.0]])


def test_a_listed_track_boxed_without_crossing_rays_gets_an_empty_entry():
    found = rays_through_boxes([np.array([[0.0, 20.0, 0.0]])], [boxes(["sign"], [[10.0, 0.0, 0.0]], [0.0])],
                               np.zeros(3), {"sign"})
    assert found["sign"][0].shape == (0, 3) and found["sign"][1].shape == (0, 3)
