"""Sampling modes from a checkpoint directory, returning scenes on the output (400 x 400 x 32) grid.

- bev: layout-conditioned generation; the layout is derived from the centred crop of dataset clips.
- expand: a layout-conditioned first tile, then `tiles` outpainted windows, each shifted by half a tile
  along +x (ego forward); the whole latent canvas is decoded at once.
- forecast: the centred crop of a dataset frame is the context; roll-out to `frames` frames.
Crops keep their metric position: a crop at cells (i0, j0) of the source grid is placed at
(x_min + i0*s, y_min + j0*s) in the output grid, the rest is empty. Forecast frames share the context
frame's pose (the temporal generator is trained on scenes where the ego is stationary).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.torch import OccupancyDataset
from occgen.checkpoint import load_dit, load_vae
from occgen.data import load_clip, open_clips
from occgen.diffusion import Diffusion
from occgen.dit import OccDiT
from occgen.export import GeneratedScene, canvas_windows, place_in_grid
from occgen.forecast import rollout
from occgen.outpaint import expand
from occgen.train import encode_scaled, layout_condition
from occgen.vae import OccVAE

Progress = Callable[[int, int], None]


@dataclass
class SampleOptions:
    crop: int = 64
    count: int = 1
    sample_steps: int = 50
    guidance: float = 1.0
    tiles: int = 3
    frames: int = 13
    seed: int = 0


def _crop_lower(grid: GridSpec, origin: tuple[int, int]) -> np.ndarray:
    return grid.lower + np.array([origin[0], origin[1], 0]) * grid.voxel_size


def _clip_indices(n: int, count: int) -> list[int]:
    return sorted({int(i) for i in np.linspace(0, n - 1, count)})


@dataclass
class _Session:
    """Models and data of one sampling run."""

    vae: OccVAE
    dit: OccDiT
    scale: float
    grid: GridSpec
    clips: OccupancyDataset
    diffusion: Diffusion
    gen: torch.Generator

    def generate(self, sem: torch.Tensor, opts: SampleOptions) -> torch.Tensor:
        """Scaled latent [1, T, C, h, w] generated under the layout of class ids [T, X, Y, Z]."""
        layout = layout_condition(sem[None], self.vae.cfg.downsample)
        shape = (1, sem.shape[0], self.vae.cfg.latent_channels, *layout.shape[-2:])
        return self.diffusion.ddim_sample(self.dit, shape, opts.sample_steps, layout=layout,
                                          guidance=opts.guidance, generator=self.gen)

    def place(self, occ: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
        """Crop frames [T, X, Y, Z] at cell `origin` -> [T, *DEFAULT_GRID.shape] at their metric position."""
        lower = _crop_lower(self.grid, origin)
        return np.stack([place_in_grid(f, lower, self.grid.voxel_size, DEFAULT_GRID) for f in occ])


def _run(data: str, ckpt: str, task: str, clip_len: int | None, opts: SampleOptions, progress: Progress | None,
         make: Callable[[_Session, torch.Tensor, tuple[int, int], int], GeneratedScene]) -> list[GeneratedScene]:
    """Open models and data, then `make` one scene per chosen clip (centred crop of `opts.crop`)."""
    vae, (dit, scale) = load_vae(ckpt), load_dit(ckpt, task)
    session = _Session(vae, dit, scale, open_dataset(data).grid,
                       open_clips(data, clip_len=clip_len or dit.cfg.frames), Diffusion(dit.cfg.train_timesteps),
                       torch.Generator().manual_seed(opts.seed))
    indices = _clip_indices(len(session.clips), opts.count)
    scenes = []
    for n, index in enumerate(indices):
        sem, origin = load_clip(session.clips, index, opts.crop)
        scenes.append(make(session, sem, origin, index))
        scenes[-1].name = f"{scenes[-1].name}-{n:03d}"
        if progress is not None:
            progress(n + 1, len(indices))
    return scenes


def sample_bev(data: str, ckpt: str, opts: SampleOptions, progress: Progress | None = None) -> list[GeneratedScene]:
    """One generated clip per chosen dataset clip, conditioned on its layout."""
    def make(s: _Session, sem: torch.Tensor, origin: tuple[int, int], index: int) -> GeneratedScene:
        occ = s.vae.decode(s.generate(sem, opts) / s.scale)[0].numpy()
        return GeneratedScene("bev", s.place(occ, origin), s.clips[index]["ego_to_global"].numpy())
    return _run(data, ckpt, "spatial", None, opts, progress, make)


def sample_expand(data: str, ckpt: str, opts: SampleOptions, progress: Progress | None = None) -> list[GeneratedScene]:
    """Scenes grown by `tiles` outpainting windows from a layout-conditioned first tile."""
    def make(s: _Session, sem: torch.Tensor, origin: tuple[int, int], index: int) -> GeneratedScene:
        first = s.generate(sem, opts)
        step = max(first.shape[3] // 2, 1)
        result = expand(s.diffusion, s.dit, first, [(step, 0)] * opts.tiles, opts.sample_steps, s.gen)
        canvas = s.vae.decode(result.canvas / s.scale)[0].numpy()  # [T, Xc, Yc, Z]
        d = s.vae.cfg.downsample
        i0, j0 = result.origins[0]
        lower = _crop_lower(s.grid, origin) - np.array([i0 * d, j0 * d, 0]) * s.grid.voxel_size
        pose0 = s.clips[index]["ego_to_global"][0].numpy()
        windows = [w for t in range(canvas.shape[0])
                   for w in canvas_windows(canvas[t], lower, s.grid.voxel_size, DEFAULT_GRID)]
        return GeneratedScene("expand", np.stack([f for f, _ in windows]),
                              np.stack([pose0 @ canvas_from_window for _, canvas_from_window in windows]))
    return _run(data, ckpt, "spatial", None, opts, progress, make)


def sample_forecast(data: str, ckpt: str, opts: SampleOptions,
                    progress: Progress | None = None) -> list[GeneratedScene]:
    """`opts.frames`-frame roll-outs from single dataset frames (frame 0 = the encoded context)."""
    def make(s: _Session, sem: torch.Tensor, origin: tuple[int, int], index: int) -> GeneratedScene:
        context = encode_scaled(s.vae, sem[None], s.scale)
        latents = rollout(s.diffusion, s.dit, context, opts.frames, s.dit.cfg.future_frames, opts.sample_steps,
                          s.gen)
        frames = s.place(s.vae.decode(latents / s.scale)[0].numpy(), origin)
        pose = s.clips[index]["ego_to_global"][0].numpy()
        return GeneratedScene("forecast", frames, np.repeat(pose[None], len(frames), 0))
    return _run(data, ckpt, "temporal", 1, opts, progress, make)


MODES = {"bev": sample_bev, "expand": sample_expand, "forecast": sample_forecast}
