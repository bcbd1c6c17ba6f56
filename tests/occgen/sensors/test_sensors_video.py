import numpy as np
import torch

from occgen.video_cond import (MapConditioner, VideoDenoiser, maps_tensor, maps_video, patchify, pseudo_latent,
                               train_video_steps, unpatchify)


def _clip(seed: int, t: int = 5, h: int = 32, w: int = 64):
    """Rendered-map-like clips: labelled blocks at random depths moving one pixel a frame."""
    rng = np.random.default_rng(seed)
    sem = np.zeros((t, h, w), np.int64)
    depth = np.zeros((t, h, w), np.float32)
    for _ in range(4):
        y, x, label, d = rng.integers(0, h - 8), rng.integers(0, w - 16), rng.choice([2, 6, 12]), rng.uniform(5, 60)
        for k in range(t):
            sem[k, y:y + 8, x + k:x + k + 12] = label
            depth[k, y:y + 8, x + k:x + k + 12] = d
    return depth, sem


def test_conditioner_shapes_and_zero_init():
    depth, sem = _clip(0)
    maps = maps_tensor(depth, sem)[None]  # (1, 5, 16, 32, 64)
    cond = MapConditioner(width=64)
    out = cond(maps)
    # 5 frames -> 2 latent frames; 32 x 64 -> 4 x 8 -> 2 x 4 patches
    assert out.shape == (1, 2 * 2 * 4, 64)
    assert torch.count_nonzero(out) == 0
    z = torch.randn(1, 4, 2, 4, 8)
    assert torch.equal(unpatchify(patchify(z, 2), 4, 2, 4, 8, 2), z)
    assert pseudo_latent(maps_video(depth, sem)[None]).shape == (1, 4, 2, 4, 8)


def test_denoiser_learns_to_use_the_maps():
    clips = [_clip(s) for s in range(4)]
    maps = torch.stack([maps_tensor(d, s) for d, s in clips])
    video = torch.stack([maps_video(d, s) for d, s in clips])
    torch.manual_seed(0)
    with_maps = train_video_steps(VideoDenoiser(), maps, video, steps=60)
    torch.manual_seed(0)
    without = train_video_steps(VideoDenoiser(), maps, video, steps=60, use_maps=False)
    assert np.mean(with_maps[-10:]) < np.mean(with_maps[:10])
    assert np.mean(with_maps[-10:]) < 0.8 * np.mean(without[-10:])
