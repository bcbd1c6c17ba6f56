"""The compiled square test against a lattice whose answer is known point by point."""

from __future__ import annotations

import numpy as np

from nuplan_occ.points.box_kernels import within_square


def test_within_square_keeps_the_lattice_points_of_the_square_edges_included():
    axis = np.arange(-5, 6, dtype=np.float32)  # integer lattice: exact in float32
    x, y = np.meshgrid(axis, axis, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), np.full(x.size, 7.0, np.float32)], axis=1)
    hits = within_square(points, 1.0, -2.0, 2.0)
    truth = np.flatnonzero((np.abs(points[:, 0] - 1.0) <= 2.0) & (np.abs(points[:, 1] + 2.0) <= 2.0))
    assert len(truth) == 25  # x in -1..3, y in -4..0
    np.testing.assert_array_equal(hits, truth)
    assert len(within_square(points, 100.0, 0.0, 1.0)) == 0
