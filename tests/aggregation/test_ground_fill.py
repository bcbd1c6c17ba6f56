"""Ground height field across ring gaps: analytic plane with a kerb step and a wall."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.points import PointInputError
from nuplan_occ.aggregation.ground_fill import ground_fill_mesh


def _rings() -> np.ndarray:
    """Points on rings of radius 10..40 m every 4 m (gaps of 4 m between rings) over a road at z = 0 for
    y < 20 and a pavement at z = 0.15 beyond, plus a 3 m wall at x = 30 (scene frame)."""
    rng = np.random.default_rng(3)
    radius = np.repeat(np.arange(10.0, 41.0, 4.0), 2000)
    angle = rng.uniform(-np.pi, np.pi, len(radius))
    x, y = radius * np.cos(angle), radius * np.sin(angle)
    ground = np.stack([x, y, np.where(y < 20.0, 0.0, 0.15) + rng.normal(0, 0.01, len(x))], 1)
    wall = np.stack([np.full(3000, 30.0), rng.uniform(-5, 5, 3000), rng.uniform(0, 3, 3000)], 1)
    return np.vstack([ground, wall])


def _height_at(vertices: np.ndarray, faces: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Height of the mesh at xy (NaN where no triangle covers it), by barycentric coordinates."""
    out = np.full(len(xy), np.nan)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    for n, p in enumerate(xy):
        v0, v1, v2 = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2], p - a[:, :2]
        det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
        u = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
        w = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
        inside = (u >= -1e-9) & (w >= -1e-9) & (u + w <= 1 + 1e-9)
        if inside.any():
            k = np.flatnonzero(inside)[0]
            out[n] = a[k, 2] + u[k] * (b[k, 2] - a[k, 2]) + w[k] * (c[k, 2] - a[k, 2])
    return out


def test_gaps_between_rings_are_bridged_on_the_ground_only():
    vertices, faces = ground_fill_mesh(_rings(), max_edge_m=6.0)
    # between rings (radius 12, 16, ... m) the road and the pavement are covered at their heights
    probes = np.array([[12.0, 0.0], [0.0, -18.0], [-22.0, 5.0], [5.0, 27.0], [-3.0, 35.0]])
    z = _height_at(vertices, faces, probes)
    assert np.all(np.isfinite(z))
    assert np.allclose(z, [0.0, 0.0, 0.0, 0.15, 0.15], atol=0.03)
    # the wall is not ground: no vertex above the pavement
    assert vertices[:, 2].max() < 0.2
    # inside the innermost ring (20 m across) nothing is bridged
    assert np.all(np.isnan(_height_at(vertices, faces, np.array([[0.0, 0.0], [3.0, -2.0]]))))


def test_ground_fill_inputs():
    with pytest.raises(PointInputError, match="points_scene"):
        ground_fill_mesh(np.zeros((4, 2)))
    vertices, faces = ground_fill_mesh(np.zeros((2, 3)))
    assert vertices.shape == (0, 3) and faces.shape == (0, 3)
