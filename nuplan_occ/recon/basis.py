"""Quadratic B-spline basis on a voxel lattice (the basis of NKSR, Huang et al., CVPR 2023).

Coordinates are level-0 voxel units u. A level of voxel size s (= 2**l) has basis centres at
(i + 0.5) * s; the basis of voxel j is B((u - c_j) / s) = b(t_x) b(t_y) b(t_z) with the standard
(partition-of-unity) quadratic B-spline b(t) = 0.75 - t^2 on |t| < 0.5, 0.5 (|t| - 1.5)^2 on
0.5 <= |t| < 1.5, else 0. A query therefore touches the 27 voxels around its own voxel.
"""

from __future__ import annotations

import torch

OFFSETS = torch.stack(
    torch.meshgrid(*(torch.arange(-1, 2),) * 3, indexing="ij"), dim=-1
).reshape(27, 3)
"""(27, 3) int64 neighbour offsets, x slowest."""


def bspline_weights(frac: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """b and b' at t = frac - o for the three voxels o = -1, 0, 1 around a query.

    frac: (..., 3) position inside the own voxel relative to its centre, in [-0.5, 0.5).
    Returns values and derivatives of shape (..., 3, 3) (last axis: o = -1, 0, 1).
    """
    values = torch.stack([0.5 * (frac - 0.5) ** 2, 0.75 - frac * frac, 0.5 * (frac + 0.5) ** 2], dim=-1)
    derivs = torch.stack([frac - 0.5, -2.0 * frac, frac + 0.5], dim=-1)
    return values, derivs


def _outer(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """(K, 27) products x[o_x] y[o_y] z[o_z] of (K, 3) factors, ordered like OFFSETS."""
    return (x[:, :, None, None] * y[:, None, :, None] * z[:, None, None, :]).reshape(-1, 27)


def stencil(u: torch.Tensor, size: int, gradient: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Basis terms of the 27 voxels of a level (voxel size `size`) around query points.

    u: (K, 3) float, level-0 voxel units. Returns (ijk (K, 27, 3) int64 voxel coordinates at that
    level, values (K, 27), gradients (K, 27, 3) with respect to u, or None when not asked).
    """
    v = u / size
    base = torch.floor(v)
    b, db = bspline_weights(v - base - 0.5)  # (K, 3 axes, 3 offsets)
    bx, by, bz = b.unbind(dim=1)
    values = _outer(bx, by, bz)
    grads = None
    if gradient:
        dx, dy, dz = db.unbind(dim=1)
        grads = torch.stack([_outer(dx, by, bz), _outer(bx, dy, bz), _outer(bx, by, dz)], dim=2) / size
    return base.to(torch.int64).unsqueeze(1) + OFFSETS, values, grads


def gram_weights(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(27,) regulariser entries K_ij = B(c_i - c_j) for the 27 same-level neighbour offsets."""
    b, _ = bspline_weights(torch.zeros(1, 3, dtype=dtype))
    return _outer(*b.unbind(dim=1))[0]
