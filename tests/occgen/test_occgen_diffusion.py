import torch

from occgen.configs import get_config
from occgen.diffusion import Diffusion
from occgen.dit import OccDiT
from occgen.layout import LAYOUT_CHANNELS


def _dit(seed=0):
    torch.manual_seed(seed)
    return OccDiT(get_config("tiny").dit, 4, LAYOUT_CHANNELS)


def test_dit_maps_latent_sequences_to_noise_of_the_same_shape():
    dit = _dit()
    z = torch.randn(2, 3, 4, 8, 8)
    out = dit(z, torch.tensor([3, 900]), torch.rand(2, 3, LAYOUT_CHANNELS, 8, 8),
              torch.tensor([[True, False, False]] * 2))
    assert out.shape == z.shape


def test_temporal_blocks_mix_frames_and_spatial_blocks_mix_positions():
    dit = _dit()
    for p in dit.parameters():  # leave adaLN-zero: give the blocks non-zero gates
        torch.nn.init.normal_(p, std=0.05)
    z = torch.randn(1, 3, 4, 8, 8)
    t = torch.tensor([10])
    base = dit(z, t)
    moved = z.clone()
    moved[0, 2, :, 6:, 6:] += 1.0  # change the last frame, last patch only
    diff = (dit(moved, t) - base).abs()
    assert diff[0, 0].sum() > 0 and diff[0, 0, :, :2, :2].sum() > 0


def test_diffusion_loss_excludes_context_frames():
    diffusion = Diffusion(100)
    z0 = torch.randn(2, 4, 4, 8, 8)
    ctx = torch.tensor([[True, False, False, False]] * 2)

    def model(z, t, layout, context):
        out = torch.zeros_like(z)
        out[:, 0] = 1e4  # garbage on the context frame only
        return out

    loss = diffusion.training_loss(model, z0, context=ctx, generator=torch.Generator().manual_seed(0))
    assert 0.8 < loss.item() < 1.2  # = mean(noise^2) over the future frames


def test_condition_is_dropped_with_the_configured_probability():
    diffusion = Diffusion(100)
    seen = []

    def model(z, t, layout, context):
        seen.extend((layout.flatten(1).abs().sum(1) == 0).tolist())
        return torch.zeros_like(z)

    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        diffusion.training_loss(model, torch.randn(50, 1, 2, 2, 2), torch.ones(50, 1, 3, 2, 2), generator=gen)
    assert 0.07 < sum(seen) / len(seen) < 0.13


def test_ddim_recovers_a_point_mass_with_the_exact_noise_predictor():
    diffusion = Diffusion(1000)
    target = torch.full((1, 1, 2, 4, 4), 0.7)

    def oracle(z, t, layout, context):
        ab = diffusion.alpha_bar[t].reshape(-1, 1, 1, 1, 1)
        return (z - ab.sqrt() * target) / (1 - ab).sqrt()

    out = diffusion.ddim_sample(oracle, tuple(target.shape), 10, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(out, target, atol=1e-4)


def test_guidance_one_is_the_conditional_prediction_and_other_scales_extrapolate():
    diffusion = Diffusion(100)
    calls = []

    def model(z, t, layout, context):
        calls.append(layout is None)
        return torch.zeros_like(z) if layout is None else torch.ones_like(z)

    z, t, lay = torch.zeros(1, 1, 1, 2, 2), torch.tensor([5]), torch.ones(1, 1, 3, 2, 2)
    assert diffusion._eps(model, z, t, lay, None, 1.0).eq(1).all() and calls == [False]
    assert diffusion._eps(model, z, t, lay, None, 3.0).eq(3).all()


def test_dit_training_loss_decreases():
    from occgen.train import train_dit
    from occgen.vae import OccVAE

    cfg = get_config("tiny")
    torch.manual_seed(0)
    vae = OccVAE(cfg.vae, depth=8).eval()
    sem = torch.zeros(4, 1, 32, 32, 8, dtype=torch.uint8)
    sem[..., 2] = 12
    sem[:, :, 8:16, 4:12, 3:5] = 2
    batches = iter(lambda: sem, None)
    _, scale, losses = train_dit(batches, vae, cfg, 60, "spatial")
    assert scale > 0
    assert sum(losses[-10:]) / 10 < 0.7 * sum(losses[:10]) / 10
