"""Video conditioning on rendered maps (paper, end of "Gaussian Point Map Rendering") and a small denoiser.

Maps of a clip: depth (T, H, W) metres (camera z, 0 = nothing rendered) and semantic ids (T, H, W);
`maps_tensor` turns them into (T, 1 + NUM_CLASSES, H, W): depth / MAX_DEPTH_M and the one-hot labels.

`MapConditioner`: per-frame 2D convs, spatial down-sampling by 8 (three stride-2 convs), causal temporal
down-sampling by 4 (the first frame is repeated 3 times in front, then a (4, 1, 1) stride-4 conv: T = 1 + 4k
frames -> 1 + k, as a CogVideoX-style causal VAE compresses time), patchify (p x p), and a zero-initialized
Linear to the denoiser width, so at initialization the conditioning adds nothing to the latent tokens.

`VideoDenoiser`: patchified latent tokens + timestep embedding + condition tokens -> transformer ->
prediction of the clean latent z0 (the paper's loss || f(z_t, t, maps) - z0 ||^2).

No camera images exist in our synthetic data and no pretrained video VAE is used, so the training target is
a stand-in: the "video" is the rendered maps themselves (semantic colours and depth, 4 channels) and its
"latent" is a parameter-free encoding (8 x 8 average pooling, frames 0, 4, 8, ...; `pseudo_latent`).
Pretrained weights load only from a local file (`load_local_state`, torch.load weights_only=True).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nuplan_occ.labels import LABELS

NUM_CLASSES = max(LABELS.names) + 1
MAX_DEPTH_M = 80.0
SPATIAL_DOWN = 8
TEMPORAL_DOWN = 4


def load_local_state(path: str | Path) -> dict:
    """torch.load of a local checkpoint with weights_only=True; URLs and missing files raise."""
    text = str(path)
    if "://" in text:
        raise ValueError(f"{text}: weights load from a local path only, not from a URL or hub")
    if not Path(text).is_file():
        raise FileNotFoundError(f"{text}: no such checkpoint file")
    return torch.load(text, map_location="cpu", weights_only=True)


def maps_tensor(depth: np.ndarray, semantic: np.ndarray) -> torch.Tensor:
    """(T, H, W) depth m and semantic ids -> (T, 1 + NUM_CLASSES, H, W) float32."""
    d = torch.from_numpy(np.clip(np.asarray(depth, dtype=np.float32) / MAX_DEPTH_M, 0.0, 1.0))[:, None]
    onehot = F.one_hot(torch.from_numpy(np.asarray(semantic, dtype=np.int64)), NUM_CLASSES).permute(0, 3, 1, 2)
    return torch.cat([d, onehot.float()], dim=1)


def pseudo_latent(video: torch.Tensor) -> torch.Tensor:
    """(B, T, C, H, W) with T = 1 + 4k -> (B, C, 1 + k, H/8, W/8): frames 0, 4, ..., 8 x 8 mean-pooled."""
    b, t, c, h, w = video.shape
    kept = video[:, ::TEMPORAL_DOWN]
    pooled = F.avg_pool2d(kept.reshape(-1, c, h, w), SPATIAL_DOWN)
    return pooled.reshape(b, kept.shape[1], c, h // SPATIAL_DOWN, w // SPATIAL_DOWN).transpose(1, 2)


def maps_video(depth: np.ndarray, semantic: np.ndarray) -> torch.Tensor:
    """The stand-in video of a clip: (T, 4, H, W) = semantic palette colour in [0, 1] and depth / MAX_DEPTH_M."""
    rgb = torch.from_numpy(LABELS.palette()[np.asarray(semantic)].astype(np.float32) / 255.0).permute(0, 3, 1, 2)
    return torch.cat([rgb, maps_tensor(depth, semantic)[:, :1]], dim=1)


def patchify(x: torch.Tensor, p: int) -> torch.Tensor:
    """(B, C, T, H, W) -> (B, T * H/p * W/p, C * p * p) tokens."""
    b, c, t, h, w = x.shape
    x = x.reshape(b, c, t, h // p, p, w // p, p).permute(0, 2, 3, 5, 1, 4, 6)
    return x.reshape(b, t * (h // p) * (w // p), c * p * p)


def unpatchify(tokens: torch.Tensor, c: int, t: int, h: int, w: int, p: int) -> torch.Tensor:
    """Inverse of `patchify`."""
    b = tokens.shape[0]
    x = tokens.reshape(b, t, h // p, w // p, c, p, p).permute(0, 4, 1, 2, 5, 3, 6)
    return x.reshape(b, c, t, h, w)


class MapConditioner(nn.Module):
    """(B, T, 1 + NUM_CLASSES, H, W) maps -> (B, N_tokens, width) condition tokens (zero at init)."""

    def __init__(self, width: int, hidden: int = 32, patch: int = 2):
        super().__init__()
        self.patch = patch
        layers: list[nn.Module] = [nn.Conv2d(1 + NUM_CLASSES, hidden, 3, padding=1), nn.SiLU()]
        for _ in range(int(math.log2(SPATIAL_DOWN))):
            layers += [nn.Conv2d(hidden, hidden, 3, stride=2, padding=1), nn.SiLU()]
        self.spatial = nn.Sequential(*layers)
        self.temporal = nn.Conv3d(hidden, hidden, (TEMPORAL_DOWN, 1, 1), stride=(TEMPORAL_DOWN, 1, 1))
        self.proj = nn.Linear(hidden * patch * patch, width)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        b, t, c, h, w = maps.shape
        x = self.spatial(maps.reshape(b * t, c, h, w))
        x = x.reshape(b, t, *x.shape[1:]).transpose(1, 2)  # (B, hidden, T, h', w')
        x = torch.cat([x[:, :, :1].expand(-1, -1, TEMPORAL_DOWN - 1, -1, -1), x], dim=2)  # causal padding
        x = F.silu(self.temporal(x))
        return self.proj(patchify(x, self.patch))


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding (B, dim) of diffusion times t (B,) in [0, 1]."""
    freqs = torch.exp(-math.log(1000.0) * torch.arange(dim // 2) / (dim // 2))
    angles = 1000.0 * t[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=1)


class VideoDenoiser(nn.Module):
    """Predicts z0 from a noisy latent (B, C, T', H', W'), diffusion time t (B,) and maps (optional)."""

    def __init__(self, latent_channels: int = 4, width: int = 64, depth: int = 2, heads: int = 4, patch: int = 2,
                 max_tokens: int = 4096):
        super().__init__()
        self.patch, self.width = patch, width
        self.embed = nn.Linear(latent_channels * patch * patch, width)
        self.pos = nn.Parameter(0.02 * torch.randn(1, max_tokens, width))
        self.time = nn.Sequential(nn.Linear(width, width), nn.SiLU(), nn.Linear(width, width))
        self.cond = MapConditioner(width, patch=patch)
        layer = nn.TransformerEncoderLayer(width, heads, 2 * width, dropout=0.0, batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(layer, depth, enable_nested_tensor=False)
        self.out = nn.Linear(width, latent_channels * patch * patch)

    def forward(self, z_t: torch.Tensor, t: torch.Tensor, maps: torch.Tensor | None = None) -> torch.Tensor:
        b, c, tt, h, w = z_t.shape
        x = self.embed(patchify(z_t, self.patch))
        x = x + self.pos[:, : x.shape[1]] + self.time(timestep_embedding(t, self.width))[:, None]
        if maps is not None:
            x = x + self.cond(maps)
        return unpatchify(self.out(self.blocks(x)), c, tt, h, w, self.patch)


def noisy(z0: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Variance-preserving forward process with alpha_bar(t) = cos^2(pi t / 2)."""
    ab = torch.cos(0.5 * math.pi * t).pow(2).reshape(-1, 1, 1, 1, 1)
    return ab.sqrt() * z0 + (1.0 - ab).sqrt() * torch.randn_like(z0)


def train_video_steps(model: VideoDenoiser, maps: torch.Tensor, video: torch.Tensor, steps: int,
                      lr: float = 2e-3, use_maps: bool = True, seed: int = 0) -> list[float]:
    """Adam steps of || f(z_t, t, maps) - z0 ||^2 on clips maps (B, T, 1 + NUM_CLASSES, H, W) and
    video (B, T, C, H, W) (z0 = pseudo_latent(video)); returns the loss of every step."""
    torch.manual_seed(seed)
    z0 = pseudo_latent(video)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        t = torch.rand(len(z0)) * 0.9 + 0.05
        loss = F.mse_loss(model(noisy(z0, t), t, maps if use_maps else None), z0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return losses
