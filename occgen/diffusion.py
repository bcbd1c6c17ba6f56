"""DDPM training (noise prediction, linear beta schedule) and DDIM sampling with classifier-free guidance.

Latents are [B, T, C, h, w]. Sampling can hold part of the latent fixed (`Known`):
- outpainting: the known region is replaced, before every denoising step, by the known latent noised to
  that step's level (q(z_t | z_0)), and by the clean known latent at the end;
- forecasting: the context frames are given clean at every step and flagged to the model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

Denoiser = Callable[..., torch.Tensor]


@dataclass
class Known:
    """Fixed part of a latent: values [B, T, C, h, w], mask bool broadcastable to it (True = known).

    noised: True for outpainting (known region follows the noise level), False for clean context
    frames (forecasting; `context` [B, T] is then passed to the model).
    """

    values: torch.Tensor
    mask: torch.Tensor
    noised: bool = True
    context: torch.Tensor | None = None


class Diffusion:
    """Linear-beta DDPM of `steps` steps (beta 1e-4 .. 2e-2)."""

    def __init__(self, steps: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02):
        self.steps = steps
        betas = torch.linspace(beta_start, beta_end, steps, dtype=torch.float64)
        self.alpha_bar = torch.cumprod(1.0 - betas, dim=0).float()

    def _ab(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return self.alpha_bar.to(like.device)[t].reshape(-1, *([1] * (like.ndim - 1)))

    def q_sample(self, z0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """z_t = sqrt(a_t) z0 + sqrt(1 - a_t) noise, t long [B]."""
        ab = self._ab(t, z0)
        return ab.sqrt() * z0 + (1 - ab).sqrt() * noise

    def training_loss(self, model: Denoiser, z0: torch.Tensor, layout: torch.Tensor | None = None,
                      context: torch.Tensor | None = None, cond_drop_prob: float = 0.1,
                      generator: torch.Generator | None = None) -> torch.Tensor:
        """MSE between predicted and true noise, over the non-context frames.

        layout [B, T, Cb, h, w] is zeroed per sample with probability `cond_drop_prob` (unconditional
        training for classifier-free guidance). context bool [B, T]: frames given clean, not in the loss.
        """
        b = z0.shape[0]
        t = torch.randint(0, self.steps, (b,), generator=generator)
        noise = torch.randn(z0.shape, generator=generator)
        zt = self.q_sample(z0, t, noise)
        weight = torch.ones(z0.shape[:2])
        if context is not None:
            zt = torch.where(context[:, :, None, None, None], z0, zt)
            weight = (~context).float()
        if layout is not None:
            keep = (torch.rand(b, generator=generator) >= cond_drop_prob).float()
            layout = layout * keep.reshape(-1, 1, 1, 1, 1)
        eps = model(zt, t, layout, context)
        per_frame = (eps - noise).pow(2).mean(dim=(2, 3, 4))
        return (per_frame * weight).sum() / weight.sum().clamp(min=1.0)

    def _eps(self, model: Denoiser, z: torch.Tensor, t: torch.Tensor, layout: torch.Tensor | None,
             context: torch.Tensor | None, guidance: float) -> torch.Tensor:
        cond = model(z, t, layout, context)
        if layout is None or guidance == 1.0:
            return cond
        uncond = model(z, t, None, context)
        return uncond + guidance * (cond - uncond)

    @torch.no_grad()
    def ddim_sample(self, model: Denoiser, shape: tuple[int, ...], sample_steps: int = 50,
                    layout: torch.Tensor | None = None, guidance: float = 1.0, known: Known | None = None,
                    generator: torch.Generator | None = None,
                    on_step: Callable[[int, int], None] | None = None) -> torch.Tensor:
        """Deterministic DDIM (eta = 0) from pure noise to a clean latent of `shape` [B, T, C, h, w].

        guidance: classifier-free guidance scale s, eps = eps_u + s (eps_c - eps_u) (1.0: conditional only).
        """
        b = shape[0]
        times = torch.linspace(self.steps - 1, 0, sample_steps).round().long()
        z = torch.randn(shape, generator=generator)
        context = known.context if known is not None else None
        for i, t in enumerate(times):
            if known is not None:
                fixed = self.q_sample(known.values, t.repeat(b), torch.randn(shape, generator=generator)) \
                    if known.noised else known.values
                z = torch.where(known.mask, fixed, z)
            ab = self.alpha_bar[t]
            ab_prev = self.alpha_bar[times[i + 1]] if i + 1 < len(times) else torch.tensor(1.0)
            eps = self._eps(model, z, t.repeat(b), layout, context, guidance)
            z0 = (z - (1 - ab).sqrt() * eps) / ab.sqrt()
            z = ab_prev.sqrt() * z0 + (1 - ab_prev).sqrt() * eps
            if on_step is not None:
                on_step(i + 1, len(times))
        if known is not None:
            z = torch.where(known.mask, known.values, z)
        return z
