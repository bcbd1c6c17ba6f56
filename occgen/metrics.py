"""Reconstruction metrics as in OccWorld: IoU of occupied vs empty, mIoU over the non-empty classes."""

from __future__ import annotations

import torch



class OccupancyIoU:
    """Accumulates per-class intersection / union over batches of label ids < `num_classes` (equal shapes)."""

    def __init__(self, num_classes: int = 256, empty: int = 0):
        self.num_classes, self.empty = num_classes, empty
        self.inter = torch.zeros(num_classes, dtype=torch.float64)
        self.union = torch.zeros(num_classes, dtype=torch.float64)
        self.geo = torch.zeros(2, dtype=torch.float64)  # occupied intersection, union

    def update(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        if pred.shape != target.shape:
            raise ValueError(f"prediction {tuple(pred.shape)} and target {tuple(target.shape)} differ")
        p, t = pred.reshape(-1).long(), target.reshape(-1).long()
        k = self.num_classes
        self.inter += torch.bincount(t[p == t], minlength=k)[:k].double()
        self.union += (torch.bincount(p, minlength=k)[:k] + torch.bincount(t, minlength=k)[:k]).double()
        po, to = p != self.empty, t != self.empty
        self.geo += torch.tensor([(po & to).sum().item(), (po | to).sum().item()], dtype=torch.float64)

    def compute(self) -> dict:
        """{"iou", "miou", "per_class": {id: iou}} in [0, 1]; classes never seen are left out of mIoU."""
        union = self.union - self.inter
        seen = [c for c in range(self.num_classes) if c != self.empty and union[c] > 0]
        per_class = {c: float(self.inter[c] / union[c]) for c in seen}
        return {
            "iou": float(self.geo[0] / self.geo[1]) if self.geo[1] > 0 else float("nan"),
            "miou": sum(per_class.values()) / len(per_class) if per_class else float("nan"),
            "per_class": per_class,
        }
