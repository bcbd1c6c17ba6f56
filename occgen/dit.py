"""Occupancy DiT: Latte-style spatial / temporal transformer over latent sequences [B, T, C, h, w].

Unified patchify: the BEV layout, down-sampled to (h, w), is concatenated with the latent on channels and
one p x p patch embedder turns each frame into L = (h/p)(w/p) tokens of width E. Fixed 2D sin-cos
positional and 1D sin-cos temporal embeddings are added; blocks alternate spatial attention (the L tokens
of one frame) and temporal attention (the T frames of one patch position), each modulated by the diffusion
timestep (adaLN-Zero, as in DiT). A learned embedding marks context frames (forecasting). The output
is the predicted noise, [B, T, C, h, w].
"""

from __future__ import annotations

import math

import torch
from torch import nn

from occgen.attention import SelfAttention
from occgen.configs import DiTConfig


def sincos(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding [N, dim] of float positions [N] (dim even)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half)
    angles = positions.float()[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=1)


def sincos_2d(rows: int, cols: int, dim: int) -> torch.Tensor:
    """[rows*cols, dim]: half the width encodes the row, half the column (row-major token order)."""
    r, c = torch.meshgrid(torch.arange(rows), torch.arange(cols), indexing="ij")
    return torch.cat([sincos(r.reshape(-1), dim // 2), sincos(c.reshape(-1), dim // 2)], dim=1)


class TransformerBlock(nn.Module):
    """Pre-norm attention + MLP block with adaLN-Zero modulation by a condition vector."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, elementwise_affine=False)
        self.attn = SelfAttention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, elementwise_affine=False)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, dim))
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(dim, 6 * dim))
        nn.init.zeros_(self.ada[1].weight)
        nn.init.zeros_(self.ada[1].bias)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x [N, L, E]; cond [N, E]."""
        s1, b1, g1, s2, b2, g2 = self.ada(cond)[:, None].chunk(6, dim=-1)
        x = x + g1 * self.attn(self.norm1(x) * (1 + s1) + b1)
        return x + g2 * self.mlp(self.norm2(x) * (1 + s2) + b2)


class OccDiT(nn.Module):
    """Noise predictor eps(z_t, t, layout, context) for latent sequences [B, T, C, h, w]."""

    def __init__(self, cfg: DiTConfig, latent_channels: int, layout_channels: int):
        super().__init__()
        self.cfg, self.latent_channels, self.layout_channels = cfg, latent_channels, layout_channels
        e, p = cfg.hidden, cfg.patch
        self.patchify = nn.Conv2d(latent_channels + layout_channels, e, p, stride=p)
        self.time_mlp = nn.Sequential(nn.Linear(e, e), nn.SiLU(), nn.Linear(e, e))
        self.context_embed = nn.Parameter(torch.zeros(e))
        self.spatial = nn.ModuleList(TransformerBlock(e, cfg.heads, cfg.mlp_ratio) for _ in range(cfg.depth))
        self.temporal = nn.ModuleList(TransformerBlock(e, cfg.heads, cfg.mlp_ratio) for _ in range(cfg.depth))
        self.final_norm = nn.LayerNorm(e, elementwise_affine=False)
        self.final_ada = nn.Sequential(nn.SiLU(), nn.Linear(e, 2 * e))
        self.out = nn.Linear(e, p * p * latent_channels)
        for layer in (self.final_ada[1], self.out):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def forward(self, z: torch.Tensor, t: torch.Tensor, layout: torch.Tensor | None = None,
                context: torch.Tensor | None = None) -> torch.Tensor:
        """z [B, T, C, h, w]; t long [B]; layout [B, T, Cb, h, w] (None or zeros: unconditional);
        context bool [B, T] marks frames given clean (None: none). Returns eps [B, T, C, h, w]."""
        b, nt, c, h, w = z.shape
        p, e = self.cfg.patch, self.cfg.hidden
        if h % p or w % p:
            raise ValueError(f"latent size {h}x{w} is not divisible by the patch size {p}")
        if layout is None:
            layout = z.new_zeros(b, nt, self.layout_channels, h, w)
        tokens = self.patchify(torch.cat([z, layout], dim=2).reshape(b * nt, -1, h, w))
        gh, gw = tokens.shape[-2:]
        x = tokens.flatten(2).transpose(1, 2).reshape(b, nt, gh * gw, e)
        x = x + sincos_2d(gh, gw, e).to(x)[None, None] + sincos(torch.arange(nt), e).to(x)[None, :, None]
        if context is not None:
            x = x + context.to(x)[:, :, None, None] * self.context_embed
        cond = self.time_mlp(sincos(t, e).to(x))  # [B, E]
        n_tok = gh * gw
        for spatial, temporal in zip(self.spatial, self.temporal):
            x = spatial(x.reshape(b * nt, n_tok, e), cond.repeat_interleave(nt, 0)).reshape(b, nt, n_tok, e)
            xt = temporal(x.transpose(1, 2).reshape(b * n_tok, nt, e), cond.repeat_interleave(n_tok, 0))
            x = xt.reshape(b, n_tok, nt, e).transpose(1, 2)
        shift, scale = self.final_ada(cond)[:, None, None].chunk(2, dim=-1)
        out = self.out(self.final_norm(x) * (1 + scale) + shift)  # [B, T, L, p*p*C]
        out = out.reshape(b, nt, gh, gw, p, p, c).permute(0, 1, 6, 2, 4, 3, 5)
        return out.reshape(b, nt, c, h, w)
