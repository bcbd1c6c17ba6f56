import pytest
import torch

from occgen.configs import get_config
from occgen.diffusion import Diffusion
from occgen.dit import OccDiT
from occgen.forecast import forecast, rollout
from occgen.layout import LAYOUT_CHANNELS
from occgen.outpaint import expand, window_origins


@pytest.fixture
def model():
    torch.manual_seed(0)
    dit = OccDiT(get_config("tiny").dit, 4, LAYOUT_CHANNELS).eval()
    for p in dit.parameters():
        torch.nn.init.normal_(p, std=0.05)
    return dit


def test_window_origins_are_shifted_to_non_negative_cells():
    assert window_origins([(4, 0), (0, -4)]) == [(0, 4), (4, 4), (4, 0)]


def test_expansion_keeps_the_known_region_and_grows_the_canvas(model):
    diffusion = Diffusion(100)
    first = torch.randn(1, 1, 4, 8, 8)
    moves = [(4, 0), (4, 0), (0, -4)]
    snapshots = []
    result = expand(diffusion, model, first, moves, sample_steps=3, generator=torch.Generator().manual_seed(0),
                    on_tile=lambda n, total: snapshots.append(n))
    assert snapshots == [1, 2, 3]
    assert result.canvas.shape == (1, 1, 4, 16, 12)
    i0, j0 = result.origins[0]
    assert (i0, j0) == (0, 4)
    # the first tile is untouched by every later window (known region under the mask)
    assert torch.equal(result.canvas[..., 0:8, 4:12], first)
    assert result.filled.sum() == 16 * 8 + 8 * 4
    # new cells are generated (not left at zero)
    assert result.canvas[..., 8:16, 4:12].abs().sum() > 0


def test_each_outpainted_window_agrees_with_the_canvas_before_it(model):
    diffusion = Diffusion(100)
    first = torch.randn(1, 2, 4, 8, 8)
    one = expand(diffusion, model, first, [(4, 0)], sample_steps=3, generator=torch.Generator().manual_seed(1))
    two = expand(diffusion, model, first, [(4, 0), (4, 0)], sample_steps=3,
                 generator=torch.Generator().manual_seed(1))
    assert torch.equal(two.canvas[..., :12, :], one.canvas)  # the second window only adds cells


def test_expansion_without_overlap_is_rejected(model):
    with pytest.raises(ValueError, match="no overlap"):
        expand(Diffusion(100), model, torch.randn(1, 1, 4, 8, 8), [(8, 0)], sample_steps=2)


def test_forecast_shapes_and_unchanged_context(model):
    context = torch.randn(2, 1, 4, 8, 8)
    out = forecast(Diffusion(100), model, context, future_frames=6, sample_steps=2)
    assert out.shape == (2, 7, 4, 8, 8)
    assert torch.equal(out[:, :1], context)
    assert not torch.equal(out[:, 1], out[:, 2])


@pytest.mark.parametrize("total, rounds", [(7, 1), (13, 2), (10, 2), (1, 0)])
def test_rollout_length_and_rounds(model, total, rounds):
    context = torch.randn(1, 1, 4, 8, 8)
    seen = []
    out = rollout(Diffusion(100), model, context, total, future_frames=6, sample_steps=2,
                  on_round=lambda r, n: seen.append(r))
    assert out.shape == (1, total, 4, 8, 8)
    assert torch.equal(out[:, 0], context[:, 0]) and len(seen) == rounds
    with pytest.raises(ValueError):
        rollout(Diffusion(100), model, torch.randn(1, 2, 4, 8, 8), 1)
