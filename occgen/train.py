"""Training loops (pure torch): the VAE on semantic clips, the DiT on scaled VAE latents.

Batches are long [B, T, X, Y, Z] class ids (see `occgen.data.semantics_batches`). The DiT trains on
latents multiplied by `latent_scale` = 1 / std of the encoder means, so they have about unit variance.
Tasks: "spatial" (layout-conditioned, layout dropped with p = cond_drop_prob) and "temporal"
(T_c context + T_f future frames, no layout, loss on the future frames).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import torch

from occgen.configs import OccGenConfig
from occgen.diffusion import Diffusion
from occgen.dit import OccDiT
from occgen.forecast import context_mask
from occgen.layout import LAYOUT_CHANNELS, downsample_layout, layout_from_semantics
from occgen.losses import vae_loss
from occgen.vae import OccVAE

StepCallback = Callable[[int, dict[str, float]], None]


def train_vae(batches: Iterator[torch.Tensor], cfg: OccGenConfig, depth: int, steps: int, seed: int = 0,
              on_step: StepCallback | None = None, vae: OccVAE | None = None) -> tuple[OccVAE, list[dict[str, float]]]:
    """Train (or continue training) a VAE for `steps` steps; returns it and the per-step loss terms."""
    torch.manual_seed(seed)
    vae = vae if vae is not None else OccVAE(cfg.vae, depth)
    vae.train()
    opt = torch.optim.AdamW(vae.parameters(), lr=cfg.lr)
    history = []
    for step in range(steps):
        sem = next(batches)
        logits, mean, logvar = vae(sem)
        terms = vae_loss(logits, vae.class_index(sem), mean, logvar, cfg.loss)
        opt.zero_grad()
        terms["total"].backward()
        opt.step()
        record = {k: float(v.detach()) for k, v in terms.items()}
        history.append(record)
        if on_step is not None:
            on_step(step + 1, record)
    return vae.eval(), history


@torch.no_grad()
def latent_scale(vae: OccVAE, batches: Iterator[torch.Tensor], n_batches: int = 4) -> float:
    """1 / std of the encoder means over `n_batches` batches."""
    means = torch.cat([vae.encode(next(batches))[0].reshape(-1) for _ in range(n_batches)])
    return float(1.0 / means.std().clamp(min=1e-6))


@torch.no_grad()
def encode_scaled(vae: OccVAE, sem: torch.Tensor, scale: float) -> torch.Tensor:
    """Scaled latent means [B, T, C, h, w] of class ids [B, T, X, Y, Z]."""
    return vae.encode(sem)[0] * scale


def layout_condition(sem: torch.Tensor, factor: int) -> torch.Tensor:
    """Layout of class ids [B, T, X, Y, Z] down-sampled to the latent grid: [B, T, Cb, X/d, Y/d]."""
    return downsample_layout(layout_from_semantics(sem), factor)


def train_dit(batches: Iterator[torch.Tensor], vae: OccVAE, cfg: OccGenConfig, steps: int, task: str,
              seed: int = 0, on_step: StepCallback | None = None) -> tuple[OccDiT, float, list[float]]:
    """Train a DiT on a frozen VAE; returns (DiT, latent scale, per-step losses)."""
    if task not in ("spatial", "temporal"):
        raise ValueError(f"unknown DiT task {task!r} (spatial, temporal)")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    vae.eval()
    scale = latent_scale(vae, batches)
    dit = OccDiT(cfg.dit, cfg.vae.latent_channels, LAYOUT_CHANNELS).train()
    diffusion = Diffusion(cfg.dit.train_timesteps)
    opt = torch.optim.AdamW(dit.parameters(), lr=cfg.lr)
    history = []
    for step in range(steps):
        sem = next(batches)
        z = encode_scaled(vae, sem, scale)
        if task == "spatial":
            loss = diffusion.training_loss(dit, z, layout_condition(sem, cfg.vae.downsample),
                                           cond_drop_prob=cfg.dit.cond_drop_prob, generator=gen)
        else:
            ctx = context_mask(z.shape[0], cfg.dit.context_frames, z.shape[1] - cfg.dit.context_frames)
            loss = diffusion.training_loss(dit, z, context=ctx, generator=gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
        if on_step is not None:
            on_step(step + 1, {"loss": history[-1]})
    return dit.eval(), scale, history


def clip_len_for(cfg: OccGenConfig, what: str) -> int:
    """Frames per training clip: VAE clip_len, spatial DiT `frames`, temporal DiT T_c + T_f."""
    return {"vae": cfg.clip_len, "spatial": cfg.dit.frames,
            "temporal": cfg.dit.context_frames + cfg.dit.future_frames}[what]
