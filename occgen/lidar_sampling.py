"""Occupancy-prior ray sampling of the learned LiDAR model, and the per-point occupancy cues.

Frames: the label grid is indexed [x, y, z] on a `GridSpec` in the ego frame (rear axle, x forward,
y left, z up); ray origins o (R, 3) and unit directions d (R, 3) are in that frame; distances s along a
ray are metres from its origin.

Sampling (the paper's occupancy-prior sampling, with visibility): the ray is marched at `march_step`
over [near, far] and the occupancy prior looked up at every march point. The sampling PDF over the
march intervals is 1 on the intervals around the first occupied march point (the visible surface:
`before` intervals in front of it, `after` behind it) and `floor` elsewhere, so that the fraction
`floor_mass` of the samples still spreads over the whole ray; a ray that meets no occupied voxel gets
a uniform PDF. `n` points are drawn by inverse CDF (stratified, optionally jittered).
"""

from __future__ import annotations

import torch

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import EMPTY, GENERIC_OBJECT, OTHER_GROUND, ROAD, ROAD_LINE, VEHICLE

N_GROUPS = 5
"""Class groups of the occupancy cues: any occupied, ground, road line, objects, other."""


def group_table() -> torch.Tensor:
    """(256, N_GROUPS) float: label id -> memberships of (any, ground, road line, objects, other)."""
    ids = torch.arange(256)
    ground = (ids == ROAD) | (ids == OTHER_GROUND)
    objects = (ids >= VEHICLE) & (ids <= GENERIC_OBJECT)
    occupied = ids != EMPTY
    line = ids == ROAD_LINE
    return torch.stack([occupied, ground, line, objects, occupied & ~ground & ~line & ~objects], dim=1).float()


GROUPS = group_table()


def lookup(labels: torch.Tensor, grid: GridSpec, pts: torch.Tensor) -> torch.Tensor:
    """Label grid (X, Y, Z) uint8 read at points (..., 3) m (ego frame); EMPTY outside the grid."""
    idx = torch.floor((pts - torch.as_tensor(grid.lower, dtype=pts.dtype)) / grid.voxel_size).long()
    shape = torch.tensor(labels.shape)
    inside = ((idx >= 0) & (idx < shape)).all(-1)
    idx = torch.minimum(torch.clamp(idx, min=0), shape - 1)
    return torch.where(inside, labels[idx[..., 0], idx[..., 1], idx[..., 2]], torch.zeros((), dtype=labels.dtype))


def point_cues(labels: torch.Tensor, grid: GridSpec, pts: torch.Tensor) -> torch.Tensor:
    """Sub-voxel cues at points (..., 3) m: class-group memberships of the voxel holding the point
    (N_GROUPS) and the point's position inside that voxel, each coordinate in [-1, 1) (3)."""
    frac = torch.remainder((pts - torch.as_tensor(grid.lower, dtype=pts.dtype)) / grid.voxel_size, 1.0)
    return torch.cat([GROUPS[lookup(labels, grid, pts).long()], frac * 2.0 - 1.0], dim=-1)


def first_hit(occupied: torch.Tensor) -> torch.Tensor:
    """Index (R,) of the first True of occupancy (R, M) bool at the march interval ends; M on a miss."""
    m = occupied.shape[1]
    return torch.where(occupied.any(1), occupied.float().argmax(1), torch.full((len(occupied),), m))


def first_hit_pdf(k: torch.Tensor, m: int, before: int, after: int, floor: float) -> torch.Tensor:
    """PDF (R, m) over m march intervals: 1 on intervals [k - before, k + after] around the first
    occupied one k (R,), `floor` elsewhere; uniform on a miss (k = m)."""
    j = torch.arange(m)[None]
    window = (j >= k[:, None] - before) & (j <= k[:, None] + after)
    pdf = torch.where(window, 1.0, floor)
    return torch.where((k < m)[:, None], pdf, torch.ones_like(pdf))


def sample_along(pdf: torch.Tensor, edges: torch.Tensor, n: int, jitter: bool) -> torch.Tensor:
    """(R, n) sorted distances drawn by inverse CDF from a piecewise-constant PDF (R, M) on `edges` (M+1,)."""
    cdf = torch.cumsum(pdf, 1)
    cdf = torch.cat([torch.zeros(len(pdf), 1), cdf / cdf[:, -1:]], dim=1)
    u = ((torch.arange(n) + 0.5) / n).expand(len(pdf), -1).contiguous()
    if jitter:
        u = torch.clamp(u + (torch.rand_like(u) - 0.5) / n, 0.0, 1.0 - 1e-6)
    i = torch.clamp(torch.searchsorted(cdf, u, right=True) - 1, 0, pdf.shape[1] - 1)
    lo, hi = cdf.gather(1, i), cdf.gather(1, i + 1)
    s = edges[i] + (u - lo) / torch.clamp(hi - lo, min=1e-9) * (edges[i + 1] - edges[i])
    return torch.sort(s, dim=1).values


def occupancy_prior_samples(labels: torch.Tensor, grid: GridSpec, o: torch.Tensor, d: torch.Tensor, n: int,
                            near: float, far: float, march_step: float, before: int, after: int,
                            floor_mass: float, jitter: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays o, d (R, 3) -> (R, n) sorted sample distances (m) (see the module docstring) and the
    free-space depth (R,) m: the march point before the first occupied one (`far` on a miss), in front of
    which the ray crosses no occupied march point."""
    m = max(1, int(round((far - near) / march_step)))
    edges = torch.linspace(near, far, m + 1)
    occupied = lookup(labels, grid, o[:, None] + edges[None, 1:, None] * d[:, None]) != EMPTY
    width = before + after + 1
    floor = floor_mass / (1.0 - floor_mass) * width / m
    k = first_hit(occupied)
    return sample_along(first_hit_pdf(k, m, before, after, floor), edges, n, jitter), edges[k]
