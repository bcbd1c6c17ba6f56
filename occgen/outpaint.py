"""Spatial expansion by 3D latent outpainting, iterated to grow a scene beyond one grid.

A window of the tile's latent size moves over a latent canvas [B, T, C, Hc, Wc] (cells of d x d voxels,
canvas axis 3 = ego x, axis 4 = ego y of the first tile). Each new window overlaps the cells generated
so far; those are the known region (mask), re-noised to each step's level during DDIM sampling and
copied exactly at the end, so the canvas never changes where it was already filled.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from occgen.diffusion import Denoiser, Diffusion, Known


@dataclass
class Expansion:
    """canvas [B, T, C, Hc, Wc]; filled bool [Hc, Wc]; origins: (row, col) latent cell of each window."""

    canvas: torch.Tensor
    filled: torch.Tensor
    origins: list[tuple[int, int]]
    tile: tuple[int, int]


def window_origins(moves: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """Window origins (latent cells, all >= 0) of a start window followed by relative `moves`."""
    path = [(0, 0)]
    for di, dj in moves:
        path.append((path[-1][0] + int(di), path[-1][1] + int(dj)))
    lo_i, lo_j = min(p[0] for p in path), min(p[1] for p in path)
    return [(i - lo_i, j - lo_j) for i, j in path]


def expand(diffusion: Diffusion, model: Denoiser, first: torch.Tensor, moves: Sequence[tuple[int, int]],
           sample_steps: int = 50, generator: torch.Generator | None = None,
           on_tile: Callable[[int, int], None] | None = None) -> Expansion:
    """Grow the canvas from the latent `first` [B, T, C, h, w] by one outpainted window per move.

    Each move (di, dj) shifts the window by latent cells; it must keep an overlap (|di| < h or |dj| < w,
    and the window must touch filled cells), else ValueError.
    """
    b, nt, c, h, w = first.shape
    origins = window_origins(moves)
    rows = max(i for i, _ in origins) + h
    cols = max(j for _, j in origins) + w
    canvas = first.new_zeros(b, nt, c, rows, cols)
    filled = torch.zeros(rows, cols, dtype=torch.bool)
    i0, j0 = origins[0]
    canvas[..., i0:i0 + h, j0:j0 + w] = first
    filled[i0:i0 + h, j0:j0 + w] = True
    for n, (i, j) in enumerate(origins[1:], start=1):
        mask = filled[i:i + h, j:j + w]
        if not mask.any():
            raise ValueError(f"expansion move {n} {tuple(moves[n - 1])} leaves no overlap with the scene")
        known = Known(canvas[..., i:i + h, j:j + w].clone(), mask.reshape(1, 1, 1, h, w), noised=True)
        canvas[..., i:i + h, j:j + w] = diffusion.ddim_sample(model, (b, nt, c, h, w), sample_steps,
                                                              known=known, generator=generator)
        filled[i:i + h, j:j + w] = True
        if on_tile is not None:
            on_tile(n, len(origins) - 1)
    return Expansion(canvas, filled, origins, (h, w))
