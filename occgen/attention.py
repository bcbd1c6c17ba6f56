"""Multi-head self-attention on token sequences, and 3D axial attention over (T, h, w) feature volumes."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class SelfAttention(nn.Module):
    """Multi-head self-attention on [N, L, E] tokens (scaled dot product, no mask)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"attention width {dim} is not divisible by {heads} heads")
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, length, dim = x.shape
        qkv = self.qkv(x).reshape(n, length, 3, self.heads, dim // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.proj(out.transpose(1, 2).reshape(n, length, dim))


class AxialAttention3d(nn.Module):
    """Residual self-attention along T, then h, then w of a [B, C, T, h, w] volume.

    Each axis attends with the two other axes folded into the batch, so the cost is linear in the
    volume size times the axis length, and T = 1 works (the T pass is then a per-cell projection).
    """

    AXES = (2, 3, 4)

    def __init__(self, channels: int, heads: int):
        super().__init__()
        self.norms = nn.ModuleList(nn.LayerNorm(channels) for _ in self.AXES)
        self.attns = nn.ModuleList(SelfAttention(channels, heads) for _ in self.AXES)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for axis, norm, attn in zip(self.AXES, self.norms, self.attns):
            moved = x.movedim(1, -1).movedim(axis - 1, -2)  # [..., L_axis, C]
            lead = moved.shape[:-2]
            seq = moved.reshape(-1, *moved.shape[-2:])
            out = attn(norm(seq)).reshape(*lead, *moved.shape[-2:])
            x = x + out.movedim(-2, axis - 1).movedim(-1, 1)
        return x
