"""VAE losses (following OccWorld): cross-entropy + Lovasz-softmax (Berman et al. 2018) + KL."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from occgen.configs import LossConfig


def lovasz_grad(fg_sorted: torch.Tensor) -> torch.Tensor:
    """Gradient of the Lovasz extension of the Jaccard loss w.r.t. errors sorted in decreasing order.

    fg_sorted: float [N, ...] ground-truth membership (0/1) in that order, one column per class. Row i is
    J(first i+1 errors) - J(first i errors), J = 1 - |fg \\ errors| / |fg U errors|.
    """
    total = fg_sorted.sum(dim=0)
    intersection = total - fg_sorted.cumsum(0)
    union = total + (1.0 - fg_sorted).cumsum(0)
    jaccard = 1.0 - intersection / union
    return torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]])


def lovasz_softmax(probs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Mean over the classes present in `labels` of the Lovasz hinge on class probabilities.

    probs: [N, K] softmax probabilities; labels: [N] class ids. With one-hot probabilities the value
    of a class equals its Jaccard loss 1 - IoU. All present classes are sorted in one call.
    """
    classes = torch.unique(labels)
    fg = (labels[:, None] == classes[None]).to(probs.dtype)  # [N, P]
    errors = (fg - probs[:, classes]).abs()
    errors_sorted, order = torch.sort(errors, dim=0, descending=True)
    grads = lovasz_grad(torch.gather(fg, 0, order))
    return (errors_sorted * grads).sum(dim=0).mean()


def kl_divergence(mean: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mean, exp(logvar)) || N(0, 1)), averaged over all latent elements."""
    return 0.5 * torch.mean(mean.pow(2) + logvar.exp() - 1.0 - logvar)


def vae_loss(logits: torch.Tensor, target: torch.Tensor, mean: torch.Tensor, logvar: torch.Tensor,
             weights: LossConfig) -> dict[str, torch.Tensor]:
    """Terms and weighted total. logits [B, K, T, X, Y, Z]; target: class indices long [B, T, X, Y, Z]."""
    ce = F.cross_entropy(logits, target)
    probs = logits.softmax(dim=1).movedim(1, -1).reshape(-1, logits.shape[1])
    ls = lovasz_softmax(probs, target.reshape(-1))
    kl = kl_divergence(mean, logvar)
    return {"ce": ce, "lovasz": ls, "kl": kl, "total": weights.ce * ce + weights.lovasz * ls + weights.kl * kl}
