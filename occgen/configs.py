"""Model and training configurations: `tiny` (CPU tests), and the 32 / 512 compression configs.

Compression ratio (OccWorld / OccSora / UniScene tables; the paper gives no formula): input size per
frame over latent size per frame, H*W*D / (h*w*C), with h = H/d, w = W/d, so ratio = d*d*D / C.
On the 400 x 400 x 32 grid (D = 32): d = 4, C = 16 gives 32; d = 8, C = 4 gives 512. The `tiny*`
configs keep those latent shapes with small networks, for CPU runs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from nuplan_occ.labels import LABELS

CLASS_IDS: tuple[int, ...] = tuple(sorted(LABELS.names))
"""Semantic label ids in class-index order (the models use contiguous indices 0..K-1)."""
NUM_CLASSES = len(CLASS_IDS)


@dataclass(frozen=True)
class VAEConfig:
    """Occupancy VAE. channels: encoder widths, one down-sampling (x2 in x and y) between consecutive
    entries, so d = 2 ** (len(channels) - 1); class_dim = C'; latent_channels = C."""

    class_dim: int = 4
    channels: tuple[int, ...] = (16, 32, 32)
    latent_channels: int = 16
    attn_heads: int = 2

    @property
    def downsample(self) -> int:
        """Spatial down-sampling factor d (x and y; time is not down-sampled)."""
        return 2 ** (len(self.channels) - 1)


@dataclass(frozen=True)
class LossConfig:
    """L = ce * CE + lovasz * Lovasz-softmax + kl * KL (lambda_1 = lovasz, lambda_2 = kl)."""

    ce: float = 1.0
    lovasz: float = 1.0
    kl: float = 1e-4


@dataclass(frozen=True)
class DiTConfig:
    """Latte-style latent DiT; `depth` pairs of (spatial, temporal) blocks; patch in latent cells."""

    patch: int = 2
    hidden: int = 64
    depth: int = 2
    heads: int = 4
    mlp_ratio: float = 2.0
    train_timesteps: int = 1000
    cond_drop_prob: float = 0.1
    frames: int = 1
    context_frames: int = 1
    future_frames: int = 6


@dataclass(frozen=True)
class OccGenConfig:
    name: str
    vae: VAEConfig = field(default_factory=VAEConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    dit: DiTConfig = field(default_factory=DiTConfig)
    lr: float = 2e-3
    batch_size: int = 2
    clip_len: int = 1

    def to_dict(self) -> dict:
        return asdict(self)


def compression_ratio(vae: VAEConfig, depth: int) -> float:
    """H*W*D / (h*w*C) for a grid of `depth` z cells: d*d*D / C."""
    return vae.downsample ** 2 * depth / vae.latent_channels


CONFIGS: dict[str, OccGenConfig] = {
    "tiny": OccGenConfig("tiny", VAEConfig(4, (16, 32, 32), 16, 2)),
    "tiny512": OccGenConfig("tiny512", VAEConfig(4, (16, 32, 32, 32), 4, 2)),
    "c32": OccGenConfig("c32", VAEConfig(8, (64, 128, 128), 16, 4), dit=DiTConfig(hidden=256, depth=6, heads=8),
                        lr=5e-4, batch_size=4),
    "c512": OccGenConfig("c512", VAEConfig(8, (64, 128, 128, 128), 4, 4),
                         dit=DiTConfig(patch=1, hidden=256, depth=6, heads=8), lr=5e-4, batch_size=4),
}


def get_config(name: str) -> OccGenConfig:
    """The named configuration; KeyError names the known ones."""
    try:
        return CONFIGS[name]
    except KeyError:
        raise KeyError(f"unknown occgen config {name!r} (known: {sorted(CONFIGS)})") from None
