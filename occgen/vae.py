"""Occupancy VAE: semantic grid sequence <-> continuous BEV latent sequence.

Input: semantic label ids, [B, T, X, Y, Z] (ego frame, [x, y, z] indexed). Each class has a learnable
embedding of C' values; stacking the Z cells of a column gives the BEV tensor [B, Z*C', T, X, Y]. A 3D CNN
over (T, X, Y) with 3D axial attention down-samples x and y by d into the latent [B, T, C, X/d, Y/d]
(mean and log-variance). The decoder mirrors it back to [B, Z*C', T, X, Y]; class logits are the dot
products of each voxel's C' features with the class embeddings, [B, K, T, X, Y, Z] over the class indices
of `CLASS_IDS`; argmax at inference, mapped back to label ids.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from occgen.attention import AxialAttention3d
from occgen.configs import CLASS_IDS, VAEConfig


class Conv3x3x3(nn.Conv3d):
    """3 x 3 x 3 convolution over (T, X, Y), zero padded by 1 (stride 1 in T).

    On a single frame (T = 1) only the centre temporal tap meets non-padding input, so it convolves with
    that 1 x 3 x 3 slice of the same weights: the same result at a third of the cost.
    """

    def __init__(self, cin: int, cout: int, stride: tuple[int, int, int] = (1, 1, 1)):
        super().__init__(cin, cout, 3, stride=stride, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[2] == 1:
            return F.conv3d(x, self.weight[:, :, 1:2], self.bias, self.stride, (0, 1, 1))
        return super().forward(x)


def _norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(min(8, channels), channels)


class ResBlock3d(nn.Module):
    """Pre-norm residual block of two 3x3x3 convolutions over (T, X, Y)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(
            _norm(cin), nn.SiLU(), Conv3x3x3(cin, cout),
            _norm(cout), nn.SiLU(), Conv3x3x3(cout, cout),
        )
        self.skip = nn.Conv3d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.skip(x) + self.body(x)


class Upsample(nn.Module):
    """x2 nearest up-sampling in X and Y (not T), then a 3x3x3 convolution."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = Conv3x3x3(channels, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=(1, 2, 2), mode="nearest"))


def _middle(channels: int, heads: int) -> nn.Sequential:
    return nn.Sequential(ResBlock3d(channels, channels), AxialAttention3d(channels, heads),
                         ResBlock3d(channels, channels))


class OccEncoder(nn.Module):
    """BEV tensor [B, Z*C', T, X, Y] -> (mean, logvar) [B, 2C, T, X/d, Y/d] stacked on channels."""

    def __init__(self, cfg: VAEConfig, depth: int):
        super().__init__()
        ch = cfg.channels
        layers: list[nn.Module] = [Conv3x3x3(depth * cfg.class_dim, ch[0])]
        for cin, cout in zip(ch[:-1], ch[1:]):
            layers += [ResBlock3d(cin, cout), Conv3x3x3(cout, cout, stride=(1, 2, 2))]
        layers += [_middle(ch[-1], cfg.attn_heads), _norm(ch[-1]), nn.SiLU(),
                   nn.Conv3d(ch[-1], 2 * cfg.latent_channels, 1)]
        self.net = nn.Sequential(*layers)

    def forward(self, bev: torch.Tensor) -> torch.Tensor:
        return self.net(bev)


class OccDecoder(nn.Module):
    """Latent [B, C, T, h, w] -> BEV features [B, Z*C', T, h*d, w*d]."""

    def __init__(self, cfg: VAEConfig, depth: int):
        super().__init__()
        ch = cfg.channels[::-1]
        layers: list[nn.Module] = [Conv3x3x3(cfg.latent_channels, ch[0]), _middle(ch[0], cfg.attn_heads)]
        for cin, cout in zip(ch[:-1], ch[1:]):
            layers += [ResBlock3d(cin, cout), Upsample(cout)]
        layers += [ResBlock3d(ch[-1], ch[-1]), _norm(ch[-1]), nn.SiLU(),
                   Conv3x3x3(ch[-1], depth * cfg.class_dim)]
        self.net = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z)


class OccVAE(nn.Module):
    """The occupancy VAE for grids of `depth` z cells and the label ids `class_ids`."""

    def __init__(self, cfg: VAEConfig, depth: int, class_ids: tuple[int, ...] = CLASS_IDS):
        super().__init__()
        self.cfg, self.depth, self.num_classes = cfg, depth, len(class_ids)
        lut = torch.full((256,), -1, dtype=torch.long)
        lut[list(class_ids)] = torch.arange(len(class_ids))
        self.register_buffer("id_to_index", lut, persistent=False)
        self.register_buffer("index_to_id", torch.tensor(class_ids, dtype=torch.uint8), persistent=False)
        self.class_embed = nn.Embedding(len(class_ids), cfg.class_dim)
        self.encoder = OccEncoder(cfg, depth)
        self.decoder = OccDecoder(cfg, depth)

    def _check(self, sem: torch.Tensor) -> None:
        d = self.cfg.downsample
        if sem.ndim != 5 or sem.shape[-1] != self.depth or sem.shape[2] % d or sem.shape[3] % d:
            raise ValueError(f"semantics must be [B, T, X, Y, {self.depth}] with X, Y divisible by {d}, "
                             f"got {tuple(sem.shape)}")

    def class_index(self, sem: torch.Tensor) -> torch.Tensor:
        """Label ids -> class indices (long, same shape); ValueError on ids outside the label map."""
        index = self.id_to_index[sem.long()]
        if bool((index < 0).any()):
            bad = torch.unique(sem[index < 0]).tolist()
            raise ValueError(f"semantics hold ids {bad} outside the label map {self.index_to_id.tolist()}")
        return index

    def to_bev(self, sem: torch.Tensor) -> torch.Tensor:
        """Label ids [B, T, X, Y, Z] -> BEV tensor [B, Z*C', T, X, Y]."""
        self._check(sem)
        b, t, x, y, z = sem.shape
        emb = self.class_embed(self.class_index(sem))  # [B, T, X, Y, Z, C']
        return emb.permute(0, 4, 5, 1, 2, 3).reshape(b, z * self.cfg.class_dim, t, x, y)

    def encode(self, sem: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, logvar), each [B, T, C, X/d, Y/d]."""
        stats = self.encoder(self.to_bev(sem)).transpose(1, 2)
        mean, logvar = stats.chunk(2, dim=2)
        return mean, logvar.clamp(-30.0, 20.0)

    def decode_logits(self, z: torch.Tensor) -> torch.Tensor:
        """Latent [B, T, C, h, w] -> class logits [B, K, T, h*d, w*d, Z]."""
        feats = self.decoder(z.transpose(1, 2))  # [B, Z*C', T, X, Y]
        b, _, t, x, y = feats.shape
        feats = feats.reshape(b, self.depth, self.cfg.class_dim, t, x, y)
        return torch.einsum("bzctxy,kc->bktxyz", feats, self.class_embed.weight)

    @torch.no_grad()
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latent [B, T, C, h, w] -> label ids uint8 [B, T, h*d, w*d, Z] (argmax of the logits)."""
        return self.index_to_id[self.decode_logits(z).argmax(dim=1)]

    def forward(self, sem: torch.Tensor, sample: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(logits [B, K, T, X, Y, Z] over class indices, mean, logvar); the latent is sampled (reparameterised) if `sample`."""
        mean, logvar = self.encode(sem)
        z = mean + torch.randn_like(mean) * torch.exp(0.5 * logvar) if sample else mean
        return self.decode_logits(z), mean, logvar
