"""Per-frame box refinement of a track against its own points (synthetic vehicle with known box errors)."""

from __future__ import annotations

import numpy as np
import pytest
from vehicle_surface import surface_samples

from nuplan_occ.points import PointInputError
from nuplan_occ.tracks.track_refine import TrackRefineParams, apply_correction, corrected_box, fix_gauge, refine_track
from nuplan_occ.geometry import yaw_matrix

SIZE = np.array([4.7, 1.9, 1.6])


def _views(seed: int, frames: int = 24):
    """Partial noisy views of the vehicle, each seen through a box off by a known error (x, y, z, yaw)."""
    rng = np.random.default_rng(seed)
    views, errors = [], []
    for _ in range(frames):
        p = surface_samples(rng, 3000, SIZE)
        side = [p[:, 0] > 1, p[:, 0] < -1, p[:, 1] > 0.5, p[:, 1] < -0.5][rng.integers(4)]
        p = p[side | (p[:, 2] > 0.3)][:700]
        p = p + rng.normal(0, 0.015, p.shape)
        err = np.r_[rng.normal(0, 0.08, 2), rng.normal(0, 0.04), np.radians(rng.normal(0, 1.0))]
        views.append((p - err[:3]) @ yaw_matrix(err[3]))  # p_true = Rz(err) p_box + err_t
        errors.append(err)
    return views, np.array(errors)


def _zero_mean(c: np.ndarray) -> np.ndarray:
    return fix_gauge(c, np.ones(len(c)))


def test_corrections_recover_the_box_errors_up_to_the_common_gauge():
    views, truth = _views(0)
    found = refine_track(views)
    before = np.abs(_zero_mean(truth))
    after = np.abs(_zero_mean(found) - _zero_mean(truth))
    assert after[:, :3].mean() < 0.01 and before[:, :3].mean() > 0.04      # m
    assert np.degrees(after[:, 3].mean()) < 0.15 < np.degrees(before[:, 3].mean())


def test_aligned_views_give_a_sharp_model():
    views, _ = _views(1)
    found = refine_track(views)
    model = np.vstack([apply_correction(v, c) for v, c in zip(views, found)])
    raw = np.vstack(views)
    # Distance of the points to the nearest face plane of the true (gauge-shifted) shape shrinks:
    # measured through the spread of the points on the flat side face y = +W/2.
    def side_spread(points):
        band = points[(points[:, 1] > SIZE[1] / 2 - 0.25) & (np.abs(points[:, 0]) < 1.0)
                      & (points[:, 2] > -0.45) & (points[:, 2] < 0.0)]  # body side, no wheels
        return np.std(band[:, 1])
    assert side_spread(model) < 0.5 * side_spread(raw)


def test_sparse_tracks_and_frames_are_left_alone():
    views, _ = _views(2, frames=5)
    params = TrackRefineParams(min_points=30, min_frames=3)
    sparse = [v[:10] for v in views]
    assert np.all(refine_track(sparse, params) == 0)
    mixed = [views[0], views[1][:5], views[2], views[3], views[4]]
    found = refine_track(mixed, params)
    assert np.all(found[1] == 0) and np.any(found[0] != 0)


def test_corrected_box_is_the_model_frame_in_the_boxes_frame():
    rng = np.random.default_rng(3)
    center, yaw = np.array([10.0, -4.0, 0.5]), 0.7
    c = np.array([0.1, -0.05, 0.02, np.radians(2.0)])
    p_box = rng.normal(size=(20, 3))
    p_model = apply_correction(p_box, c)
    ego_from_box = p_box @ yaw_matrix(yaw).T + center
    new_center, new_yaw = corrected_box(center, yaw, c)
    ego_from_model = p_model @ yaw_matrix(new_yaw).T + new_center
    np.testing.assert_allclose(ego_from_model, ego_from_box, atol=1e-12)


def test_bad_frames_raise():
    with pytest.raises(PointInputError, match="frame 1"):
        refine_track([np.zeros((4, 3)), np.zeros((4, 2))])


def test_smoothing_averages_box_noise_away():
    from nuplan_occ.tracks.track_refine import smooth_track_poses

    rng = np.random.default_rng(4)
    t = np.arange(40) * 0.05
    static = np.tile([5.0, 2.0, 0.8, 3.1], (40, 1))
    noisy = static + np.c_[rng.normal(0, 0.08, (40, 3)), rng.normal(0, 0.02, 40)]
    noisy[:, 3] = np.arctan2(np.sin(noisy[:, 3]), np.cos(noisy[:, 3]))  # crosses +-pi
    out = smooth_track_poses(t, noisy, np.ones(40), static=True, window_s=1.0)
    assert np.abs(out[:, :3] - static[:, :3]).max() < 0.05 and np.all(np.ptp(out, axis=0) == 0)
    assert abs(np.angle(np.exp(1j * (out[0, 3] - 3.1)))) < 0.01
    moving = np.c_[10 * t, 0.5 * t ** 2, np.full(40, 0.8), np.full(40, 0.2)]
    noisy = moving + rng.normal(0, 0.08, (40, 4)) * [1, 1, 1, 0.2]
    out = smooth_track_poses(t, noisy, np.ones(40), static=False, window_s=1.0)
    assert np.abs(out - moving)[:, :2].mean() < 0.5 * np.abs(noisy - moving)[:, :2].mean()
