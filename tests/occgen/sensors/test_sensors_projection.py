import numpy as np
import torch

from occgen.render_maps import default_rig
from occgen.unscented import ewa_project, project_points, unscented_project, ut_weights


def test_ut_weights_match_the_paper():
    lam, wm, wc = ut_weights(1.0, 2.0, 0.0)
    assert lam == 0.0
    assert np.allclose(wm, [0.0] + [1 / 6] * 6) and np.isclose(wm.sum(), 1.0)
    assert np.allclose(wc, [2.0] + [1 / 6] * 6)


def test_ut_matches_exact_projection_under_strong_distortion_while_ewa_does_not():
    cam = default_rig()[0]
    assert cam.distortion[0] < -0.3  # strong barrel distortion
    rng = np.random.default_rng(0)
    # Gaussian centres over the whole field of view, 5..40 m ahead (camera frame)
    x_n = rng.uniform(-0.7, 0.7, 400)
    y_n = rng.uniform(-0.4, 0.4, 400)
    z = rng.uniform(5.0, 40.0, 400)
    mu = torch.from_numpy(np.stack([x_n * z, y_n * z, z], axis=1))
    exact, ok = project_points(mu, cam.K, cam.distortion)
    ok &= (exact[:, 0] >= 0) & (exact[:, 0] < cam.width) & (exact[:, 1] >= 0) & (exact[:, 1] < cam.height)
    cov = (0.01**2) * torch.eye(3, dtype=torch.float64).expand(len(mu), 3, 3)
    ut_mean, ut_cov, ut_ok = unscented_project(mu, cov, cam.K, cam.distortion)
    ewa_mean, _, _ = ewa_project(mu, cov, cam.K)
    sel = ok & ut_ok
    ut_err = (ut_mean - exact)[sel].norm(dim=1)
    ewa_err = (ewa_mean - exact)[sel].norm(dim=1)
    assert sel.sum() > 200
    assert ut_err.max() < 0.05  # sub-pixel (in fact far below)
    assert ewa_err.max() > 20.0 and ewa_err.median() > 5.0
    # the projected footprint of a 1 cm Gaussian is about f * 0.01 / z pixels wide
    sigma = torch.sqrt(ut_cov[sel].diagonal(dim1=1, dim2=2).mean(1))
    expected = 1545.0 * 0.01 / mu[sel, 2]
    assert torch.allclose(sigma, expected, rtol=0.5)


def test_ut_covariance_of_a_linear_map_is_exact():
    # without distortion and at the optical axis, UT and EWA agree on the 2D covariance
    K = np.array([[1000.0, 0, 500], [0, 1000.0, 400], [0, 0, 1]])
    mu = torch.tensor([[0.0, 0.0, 10.0]], dtype=torch.float64)
    cov = torch.diag(torch.tensor([0.04, 0.09, 0.0001], dtype=torch.float64))[None]
    m_ut, c_ut, _ = unscented_project(mu, cov, K, np.zeros(5))
    m_ewa, c_ewa, _ = ewa_project(mu, cov, K)
    assert torch.allclose(m_ut, m_ewa, atol=1e-3)
    assert torch.allclose(c_ut, c_ewa, rtol=1e-2)
