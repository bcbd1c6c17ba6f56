"""Sparse Gaussian point maps: occupied voxels -> 3D Gaussians, and tile-based alpha compositing.

Each occupied voxel of a semantic grid becomes one isotropic 3D Gaussian at the voxel centre (ego
frame, metres) carrying the voxel's label, an opacity and a standard deviation `scale` (paper default
0.01 m, so the rendered maps are sparse point maps rather than dense surfaces).

`rasterize` composites projected 2D Gaussians front to back per 8 x 8 pixel tile (tiny Gaussians: small tiles waste less), as in 3D Gaussian
splatting (paper equations for D and S):
    alpha'_i(p) = min(0.99, opacity_i * exp(-0.5 (p - m_i)^T Sigma'_i^-1 (p - m_i))), dropped below 1/255,
    w_i(p) = alpha'_i(p) * prod_{j < i} (1 - alpha'_j(p)),
    D(p) = sum_i w_i d_i,  S(p) = argmax_c sum_i w_i onehot(s_i)_c,  A(p) = sum_i w_i.
Pixel centres are at integer (u, v) (OpenCV). Tiles are processed in batches padded to the largest tile
of the batch, so memory stays bounded by `budget` floats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import EMPTY

ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0


@dataclass
class GaussianSet:
    """N isotropic 3D Gaussians. means (N, 3) m in the ego frame; labels (N,) uint8 semantic ids;
    opacity (N,) in (0, 1]; scale (N,) standard deviation in metres."""

    means: np.ndarray
    labels: np.ndarray
    opacity: np.ndarray
    scale: np.ndarray

    def __len__(self) -> int:
        return int(len(self.means))


def gaussians_from_occupancy(
    semantics: np.ndarray, grid: GridSpec = DEFAULT_GRID, scale: float = 0.01, opacity: float = 1.0
) -> GaussianSet:
    """One Gaussian per voxel whose label is not EMPTY; semantics is indexed [x, y, z] on `grid`."""
    semantics = np.asarray(semantics)
    if semantics.shape != grid.shape:
        raise ValueError(f"semantics has shape {semantics.shape}, grid expects {grid.shape}")
    idx = np.argwhere(semantics != EMPTY)
    n = len(idx)
    return GaussianSet(
        means=grid.index_to_center(idx),
        labels=semantics[tuple(idx.T)].astype(np.uint8),
        opacity=np.full(n, float(opacity)),
        scale=np.full(n, float(scale)),
    )


def _tile_pairs(mean2d: torch.Tensor, radius: torch.Tensor, depth: torch.Tensor, tiles_x: int, tiles_y: int, tile: int):
    """(tile id, gaussian id) pairs for every tile a Gaussian's 3-sigma box touches, sorted by tile then depth."""
    tx0 = torch.floor((mean2d[:, 0] - radius + 0.5) / tile).long().clamp(0, tiles_x - 1)
    tx1 = torch.floor((mean2d[:, 0] + radius + 0.5) / tile).long().clamp(0, tiles_x - 1)
    ty0 = torch.floor((mean2d[:, 1] - radius + 0.5) / tile).long().clamp(0, tiles_y - 1)
    ty1 = torch.floor((mean2d[:, 1] + radius + 0.5) / tile).long().clamp(0, tiles_y - 1)
    nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
    order = torch.argsort(depth)  # depth order first, a stable sort by tile keeps it within tiles
    counts = (nx * ny)[order]
    gid = torch.repeat_interleave(order, counts)
    local = torch.arange(len(gid)) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    tile_x = tx0[gid] + local % nx[gid]
    tile_y = ty0[gid] + local // nx[gid]
    tid = tile_y * tiles_x + tile_x
    tid, perm = torch.sort(tid, stable=True)
    return tid, gid[perm]


def rasterize(
    mean2d: torch.Tensor, cov2d: torch.Tensor, depth: torch.Tensor, labels: torch.Tensor, opacity: torch.Tensor,
    width: int, height: int, num_classes: int, tile: int = 8, budget: int = 1 << 22,
) -> dict[str, np.ndarray]:
    """Composite projected Gaussians into (height, width) maps.

    mean2d (N, 2) px, cov2d (N, 2, 2) px^2 (already dilated), depth (N,) m (camera z), labels (N,) int,
    opacity (N,). Returns float32 "depth_raw" (the paper's D), "alpha" (A), "depth" (D / A where A > 0,
    else 0; metres along the optical axis) and uint8 "semantic" (argmax of S; EMPTY where no Gaussian
    contributes).
    """
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    out_d = torch.zeros(tiles_y * tiles_x, tile * tile, dtype=torch.float32)
    out_a = torch.zeros_like(out_d)
    out_s = torch.zeros(tiles_y * tiles_x, tile * tile, dtype=torch.long)
    if len(mean2d):
        det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] ** 2
        conic = torch.stack([cov2d[:, 1, 1] / det, -cov2d[:, 0, 1] / det, cov2d[:, 0, 0] / det], dim=1)
        half = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
        lam_max = half + torch.sqrt(torch.clamp(half**2 - det, min=0.0))
        radius = torch.ceil(3.0 * torch.sqrt(lam_max))
        on = ((mean2d[:, 0] + radius >= -0.5) & (mean2d[:, 0] - radius <= width - 0.5)
              & (mean2d[:, 1] + radius >= -0.5) & (mean2d[:, 1] - radius <= height - 0.5) & (det > 0))
        keep = torch.nonzero(on).squeeze(1)
        tid, gid = _tile_pairs(mean2d[keep], radius[keep], depth[keep], tiles_x, tiles_y, tile)
        gid = keep[gid]
        _composite(tid, gid, mean2d, conic, depth, labels, opacity, tiles_x, tile, num_classes, budget,
                   out_d, out_a, out_s)

    def image(t: torch.Tensor) -> np.ndarray:
        t = t.reshape(tiles_y, tiles_x, tile, tile).permute(0, 2, 1, 3).reshape(tiles_y * tile, tiles_x * tile)
        return t[:height, :width].numpy()

    depth_raw, alpha = image(out_d), image(out_a)
    safe = np.where(alpha > 0, alpha, 1.0)
    return {
        "depth_raw": depth_raw.astype(np.float32),
        "alpha": alpha.astype(np.float32),
        "depth": np.where(alpha > 0, depth_raw / safe, 0.0).astype(np.float32),
        "semantic": np.where(alpha > 0, image(out_s), EMPTY).astype(np.uint8),
    }


def _composite(tid, gid, mean2d, conic, depth, labels, opacity, tiles_x, tile, num_classes, budget,
               out_d, out_a, out_s) -> None:
    """Front-to-back compositing of the sorted (tile, gaussian) pairs into the per-tile outputs (in place)."""
    if len(tid) == 0:
        return
    tiles, counts = torch.unique_consecutive(tid, return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    by_size = torch.argsort(counts)
    offs = torch.arange(tile * tile)
    py, px = (offs // tile).float(), (offs % tile).float()
    i = 0
    while i < len(by_size):
        # tiles come in increasing size, so the batch's first tile bounds its size from below;
        # the batch is then cut so that its largest tile (the padding) fits the budget
        n_batch = max(1, budget // (int(counts[by_size[i]]) * tile * tile))
        sel = by_size[i:i + n_batch]
        k_max = int(counts[sel].max())
        sel = sel[: max(1, budget // (k_max * tile * tile))]
        rank = torch.arange(k_max)
        pair = starts[sel][:, None] + rank[None]
        valid = rank[None] < counts[sel][:, None]
        g = gid[torch.where(valid, pair, torch.zeros_like(pair))]  # (T, K)
        t = tiles[sel]
        m = mean2d[g] - torch.stack([t % tiles_x, t // tiles_x], dim=1)[:, None].double() * tile  # tile-local
        dx = px[None, None] - m[..., 0:1].float()  # (T, K, P)
        dy = py[None, None] - m[..., 1:2].float()
        c = conic[g].float()
        power = -0.5 * (c[..., 0:1] * dx * dx + 2.0 * c[..., 1:2] * dx * dy + c[..., 2:3] * dy * dy)
        alpha = torch.clamp(opacity[g].float()[..., None] * torch.exp(power), max=ALPHA_MAX)
        alpha = torch.where((alpha >= ALPHA_MIN) & valid[..., None], alpha, torch.zeros_like(alpha))
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], dim=1), dim=1)
        w = alpha * trans
        out_d[t] = (w * depth[g].float()[..., None]).sum(1)
        out_a[t] = w.sum(1)
        sem = torch.zeros(len(sel), num_classes, tile * tile, dtype=w.dtype)
        sem.scatter_add_(1, labels[g][..., None].expand_as(w).long(), w)
        out_s[t] = sem.argmax(1)
        i += len(sel)
