"""Projection of 3D Gaussians onto a distorted camera: the unscented transform and linearized EWA.

Camera frame (OpenCV, as nuPlan's camera rows): x right, y down, z forward (optical axis), metres.
Image coordinates (u, v) in pixels, OpenCV convention: the centre of pixel (column c, row r) is at
(u, v) = (c, r).

Camera model g (OpenCV / nuPlan, distortion [k1, k2, p1, p2, k3]):
    x' = X / Z, y' = Y / Z, r2 = x'^2 + y'^2, radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3,
    x'' = x' radial + 2 p1 x' y' + p2 (r2 + 2 x'^2),  y'' = y' radial + p1 (r2 + 2 y'^2) + 2 p2 x' y',
    [u, v, 1]^T = K [x'', y'', 1]^T.
The polynomial folds back beyond the radius where r * radial(r) stops increasing; points past that
radius (and points with Z <= near) are invalid: they would otherwise land inside the image a second time.

`unscented_project` follows the paper (section "Robust Calibration with Unscented Transform", after
3DGUT): 7 sigma points through g, alpha = 1, beta = 2, kappa = 0. `ewa_project` is the linearized
projection of 3D Gaussian splatting: pinhole perspective with its first-order Jacobian; a linearized pinhole
splat has no place for lens distortion, which is why it misplaces Gaussians on distorted cameras.
"""

from __future__ import annotations

import math

import numpy as np
import torch

NEAR_M = 0.1
"""Points closer than this along the optical axis (metres) do not project."""

COV_DILATION_PX2 = 0.3
"""Low-pass dilation added to projected 2D covariances (px^2), as in 3D Gaussian splatting."""


def max_valid_r2(distortion: np.ndarray, limit: float = 4.0) -> float:
    """Largest r2 = x'^2 + y'^2 (<= limit) up to which r * radial(r) is increasing (radial model only)."""
    k1, k2, _, _, k3 = (float(v) for v in np.asarray(distortion, dtype=np.float64).reshape(5))
    r2 = np.linspace(0.0, limit, 4001)
    # d/dr [r (1 + k1 r^2 + k2 r^4 + k3 r^6)] = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6
    slope = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2**2 + 7.0 * k3 * r2**3
    bad = np.nonzero(slope <= 0.0)[0]
    return float(r2[bad[0] - 1]) if len(bad) else limit


def distort(xy: torch.Tensor, distortion: torch.Tensor) -> torch.Tensor:
    """Apply [k1, k2, p1, p2, k3] to normalized image coordinates xy (..., 2); returns (..., 2)."""
    k1, k2, p1, p2, k3 = distortion.unbind(-1)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def _apply_K(xy: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    return torch.stack([u, v], dim=-1)


def project_points(points_cam: torch.Tensor, K: np.ndarray, distortion: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact nonlinear projection g of camera-frame points (..., 3) m -> (uv (..., 2) px, valid (...))."""
    K_t = torch.as_tensor(K, dtype=points_cam.dtype)
    d_t = torch.as_tensor(np.asarray(distortion, dtype=np.float64).reshape(5), dtype=points_cam.dtype)
    z = points_cam[..., 2]
    valid = z > NEAR_M
    xy = points_cam[..., :2] / torch.where(valid, z, torch.ones_like(z))[..., None]
    valid = valid & ((xy * xy).sum(-1) <= max_valid_r2(distortion))
    return _apply_K(distort(xy, d_t), K_t), valid


def ut_weights(alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0, n: int = 3) -> tuple[float, np.ndarray, np.ndarray]:
    """(lambda, mean weights (2n+1,), covariance weights (2n+1,)) of the unscented transform."""
    lam = alpha**2 * (n + kappa) - n
    w_mean = np.full(2 * n + 1, 1.0 / (2.0 * (lam + n)))
    w_cov = w_mean.copy()
    w_mean[0] = lam / (lam + n)
    w_cov[0] = w_mean[0] + (1.0 - alpha**2 + beta)
    return lam, w_mean, w_cov


def sigma_points(mu: torch.Tensor, cov: torch.Tensor, lam: float) -> torch.Tensor:
    """The 2n+1 sigma points (N, 7, 3) of Gaussians mu (N, 3), cov (N, 3, 3) (same frame as mu)."""
    L = torch.linalg.cholesky(cov)  # (N, 3, 3), columns are the factor's columns
    spread = math.sqrt(3.0 + lam) * L.transpose(1, 2)  # rows = columns of L
    return torch.cat([mu[:, None], mu[:, None] + spread, mu[:, None] - spread], dim=1)


def unscented_project(
    mu_cam: torch.Tensor, cov_cam: torch.Tensor, K: np.ndarray, distortion: np.ndarray,
    alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project Gaussians (camera frame: mu (N, 3) m, cov (N, 3, 3) m^2) with the unscented transform.

    Returns (mean (N, 2) px, covariance (N, 2, 2) px^2, valid (N,)): valid iff all 7 sigma points project.
    """
    lam, w_mean, w_cov = ut_weights(alpha, beta, kappa)
    pts = sigma_points(mu_cam, cov_cam, lam)
    uv, ok = project_points(pts, K, distortion)  # (N, 7, 2)
    wm = torch.as_tensor(w_mean, dtype=uv.dtype)
    wc = torch.as_tensor(w_cov, dtype=uv.dtype)
    mean = (wm[None, :, None] * uv).sum(1)
    diff = uv - mean[:, None]
    cov = torch.einsum("k,nki,nkj->nij", wc, diff, diff)
    return mean, cov, ok.all(dim=1)


def ewa_project(mu_cam: torch.Tensor, cov_cam: torch.Tensor, K: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Linearized (EWA) projection of 3D Gaussian splatting: pinhole mean, Jacobian J Sigma J^T.

    Inputs in the camera frame (mu (N, 3) m, cov (N, 3, 3) m^2). Distortion is not modelled.
    Returns (mean (N, 2) px, covariance (N, 2, 2) px^2, valid (N,)).
    """
    K_t = torch.as_tensor(K, dtype=mu_cam.dtype)
    x, y, z = mu_cam.unbind(-1)
    valid = z > NEAR_M
    z = torch.where(valid, z, torch.ones_like(z))
    mean = _apply_K(torch.stack([x / z, y / z], dim=-1), K_t)
    J = torch.zeros(len(mu_cam), 2, 3, dtype=mu_cam.dtype)
    J[:, 0, 0] = K_t[0, 0] / z
    J[:, 0, 1] = K_t[0, 1] / z
    J[:, 0, 2] = -(K_t[0, 0] * x + K_t[0, 1] * y) / z**2
    J[:, 1, 1] = K_t[1, 1] / z
    J[:, 1, 2] = -K_t[1, 1] * y / z**2
    cov = J @ cov_cam @ J.transpose(1, 2)
    return mean, cov, valid
