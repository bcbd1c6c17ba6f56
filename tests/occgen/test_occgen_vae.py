import pytest
import torch

from nuplan_occ.labels import ROAD, VEHICLE
from occgen.configs import CLASS_IDS, compression_ratio, get_config
from occgen.vae import Conv3x3x3, OccVAE


def test_compression_ratios_of_the_named_configs_on_the_dataset_grid():
    assert compression_ratio(get_config("tiny").vae, 32) == 32
    assert compression_ratio(get_config("c32").vae, 32) == 32
    assert compression_ratio(get_config("tiny512").vae, 32) == 512
    assert compression_ratio(get_config("c512").vae, 32) == 512
    with pytest.raises(KeyError, match="known"):
        get_config("huge")


def test_single_frame_convolution_equals_the_full_3d_convolution():
    torch.manual_seed(0)
    conv = Conv3x3x3(3, 5, stride=(1, 2, 2))
    x = torch.randn(2, 3, 1, 8, 8)
    full = torch.nn.functional.conv3d(x, conv.weight, conv.bias, conv.stride, 1)
    assert torch.allclose(conv(x), full, atol=1e-6)


def test_shapes_latent_and_decoded_label_ids():
    cfg = get_config("tiny").vae
    vae = OccVAE(cfg, depth=8)
    sem = torch.full((2, 3, 32, 32, 8), ROAD, dtype=torch.uint8)
    sem[:, :, :8, :8, 2] = VEHICLE
    mean, logvar = vae.encode(sem)
    assert mean.shape == logvar.shape == (2, 3, cfg.latent_channels, 32 // cfg.downsample, 32 // cfg.downsample)
    logits, _, _ = vae(sem)
    assert logits.shape == (2, len(CLASS_IDS), 3, 32, 32, 8)
    decoded = vae.decode(mean)
    assert decoded.shape == sem.shape and decoded.dtype == torch.uint8
    assert set(torch.unique(decoded).tolist()) <= set(CLASS_IDS)


def test_logits_are_dot_products_with_the_class_embeddings():
    vae = OccVAE(get_config("tiny").vae, depth=8)
    z = torch.randn(1, 1, vae.cfg.latent_channels, 4, 4)
    feats = vae.decoder(z.transpose(1, 2)).reshape(1, 8, vae.cfg.class_dim, 1, 16, 16)
    logits = vae.decode_logits(z)
    k, x, y, zz = 3, 5, 7, 2
    expected = feats[0, zz, :, 0, x, y] @ vae.class_embed.weight[k]
    assert torch.allclose(logits[0, k, 0, x, y, zz], expected, atol=1e-5)


def test_bad_input_is_rejected():
    vae = OccVAE(get_config("tiny").vae, depth=8)
    with pytest.raises(ValueError, match="divisible"):
        vae.encode(torch.zeros(1, 1, 30, 32, 8, dtype=torch.uint8))
    with pytest.raises(ValueError, match=r"ids \[10\]"):
        vae.encode(torch.full((1, 1, 32, 32, 8), 10, dtype=torch.uint8))
