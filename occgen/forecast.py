"""Temporal forecasting: T_f future latent frames from T_c clean context frames, and roll-out.

The context frames enter the DiT as their clean VAE latents (flagged as context) at every denoising step;
the future frames start from pure noise. Training uses the same split, with the loss on the future
frames only (`Diffusion.training_loss(context=...)`). The paper obtains the context latent by DDIM
inversion; here it is the clean encoder mean, the t = 0 end of that inversion.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from occgen.diffusion import Denoiser, Diffusion, Known


def context_mask(batch: int, context_frames: int, future_frames: int) -> torch.Tensor:
    """bool [B, T_c + T_f], True on the first T_c frames."""
    mask = torch.zeros(batch, context_frames + future_frames, dtype=torch.bool)
    mask[:, :context_frames] = True
    return mask


def forecast(diffusion: Diffusion, model: Denoiser, context: torch.Tensor, future_frames: int = 6,
             sample_steps: int = 50, generator: torch.Generator | None = None) -> torch.Tensor:
    """Context latents [B, T_c, C, h, w] -> [B, T_c + T_f, C, h, w] (context frames unchanged)."""
    b, tc, c, h, w = context.shape
    ctx = context_mask(b, tc, future_frames)
    values = torch.cat([context, context.new_zeros(b, future_frames, c, h, w)], dim=1)
    known = Known(values, ctx[:, :, None, None, None], noised=False, context=ctx)
    return diffusion.ddim_sample(model, tuple(values.shape), sample_steps, known=known, generator=generator)


def rollout(diffusion: Diffusion, model: Denoiser, context: torch.Tensor, total_frames: int,
            future_frames: int = 6, sample_steps: int = 50, generator: torch.Generator | None = None,
            on_round: Callable[[int, int], None] | None = None) -> torch.Tensor:
    """Multi-round forecasting: each round conditions on the last T_c frames so far.

    Returns [B, total_frames, C, h, w], starting with the given context frames.
    """
    tc = context.shape[1]
    if total_frames < tc:
        raise ValueError(f"total_frames {total_frames} is shorter than the {tc} context frames")
    frames = context
    rounds = -(-(total_frames - tc) // future_frames)
    for r in range(rounds):
        window = forecast(diffusion, model, frames[:, -tc:], future_frames, sample_steps, generator)
        frames = torch.cat([frames, window[:, tc:]], dim=1)
        if on_round is not None:
            on_round(r + 1, rounds)
    return frames[:, :total_frames]
