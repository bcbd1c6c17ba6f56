"""Checkpoints: `torch.save` of state dicts plus plain metadata; loaded from local paths with weights_only."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from occgen.configs import get_config
from occgen.dit import OccDiT
from occgen.layout import LAYOUT_CHANNELS
from occgen.vae import OccVAE

VAE_FILE = "vae.pt"


def dit_file(task: str) -> str:
    """File name of the DiT of a task ("spatial" or "temporal")."""
    if task not in ("spatial", "temporal"):
        raise ValueError(f"unknown DiT task {task!r} (spatial, temporal)")
    return f"dit_{task}.pt"


def _local(path: str | Path) -> Path:
    text = str(path)
    if "://" in text:
        raise ValueError(f"{text}: checkpoints are loaded from local paths only")
    return Path(text)


def save(path: str | Path, model: nn.Module, meta: dict) -> None:
    """Write {"state_dict", **meta} (meta: plain str/int/float/list values)."""
    path = _local(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": model.state_dict(), **meta}, path)


def _load(path: str | Path) -> dict:
    path = _local(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint")
    return torch.load(path, map_location="cpu", weights_only=True)


def load_vae(ckpt_dir: str | Path) -> OccVAE:
    """The VAE of `<ckpt_dir>/vae.pt` in eval mode (meta: config, depth, class_ids)."""
    data = _load(_local(ckpt_dir) / VAE_FILE)
    vae = OccVAE(get_config(data["config"]).vae, int(data["depth"]), tuple(data["class_ids"]))
    vae.load_state_dict(data["state_dict"])
    return vae.eval()


def load_dit(ckpt_dir: str | Path, task: str) -> tuple[OccDiT, float]:
    """(DiT in eval mode, latent scale) of `<ckpt_dir>/dit_<task>.pt`."""
    data = _load(_local(ckpt_dir) / dit_file(task))
    cfg = get_config(data["config"])
    dit = OccDiT(cfg.dit, cfg.vae.latent_channels, LAYOUT_CHANNELS)
    dit.load_state_dict(data["state_dict"])
    return dit.eval(), float(data["latent_scale"])
