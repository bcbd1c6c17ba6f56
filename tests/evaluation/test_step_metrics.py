"""The FBSA quality metrics on hand-made inputs."""

from __future__ import annotations

import numpy as np
import pytest

from nuplan_occ.points import PointInputError
from nuplan_occ.evaluation.step_metrics import ground_layering, moving_leak_fraction, outlier_scores, pose_errors
from nuplan_occ.geometry import make_transform, rotation_from_euler, yaw_matrix


def test_pose_errors_of_a_known_offset():
    truth = np.stack([make_transform(yaw_matrix(0.1 * i), [i, 0.0, 0.0]) for i in range(4)])
    est = truth.copy()
    est[:, :3, 3] += [0.03, 0.04, -0.02]
    est[2, :3, :3] = rotation_from_euler(np.radians(0.5), 0.0, 0.2 + np.radians(1.0))
    e = pose_errors(est, truth)
    np.testing.assert_allclose(e.horizontal_m, 0.05)
    np.testing.assert_allclose(e.z_m, -0.02)
    np.testing.assert_allclose(e.yaw_deg, [0, 0, 1.0, 0], atol=1e-9)
    np.testing.assert_allclose(e.tilt_deg, [0, 0, 0.5, 0], atol=1e-6)
    assert e.relative_translation_m[0] == pytest.approx(0.0, abs=1e-12) and e.relative_rotation_deg[1] > 1.0
    assert e.medians()["horizontal_m"] == pytest.approx(0.05)
    with pytest.raises(PointInputError):
        pose_errors(est[:3], truth)


def test_outlier_leak_and_ground_figures():
    s = outlier_scores(np.array([True, False, False, True]), np.array([False, True, False, True]))
    assert (s.caught, s.lost, s.n_outliers, s.n_real) == (0.5, 0.5, 2, 2)
    assert moving_leak_fraction(np.array([-1, 3, 3]), np.array([-1, 3, 3, 3, 4, 7]), [3, 4]) == 0.5
    assert moving_leak_fraction(np.array([1]), np.array([1]), [3]) == 0.0
    g = ground_layering(np.r_[np.full(90, 0.02), np.full(10, 0.3)], 0.0, tol=0.05)
    assert g.offset == pytest.approx(0.02) and g.within_tol == pytest.approx(0.9)
    assert g.p95_layer == pytest.approx(0.28)
    with pytest.raises(PointInputError):
        ground_layering(np.zeros(0), 0.0)
